//! Stage-1 object registration: the k-d tree against brute force, the rotation grid's
//! coverage, and recovery of random rigid motions of textured synthetic objects seen partially,
//! with noise and a change of lighting.
//!
//! Tolerances of the recovery tests: points are ~6 mm apart with ~0.6 mm RMS noise along the
//! normal, each side sees only about half of the object (fitness ~0.5), and the two sides are lit
//! differently. The estimate is the ICP fixed point of colour-guided correspondences, which stops
//! short of the best score by up to ~2.5° on these shapes (measured: ball ≤ 0.5°, vase 1.25°,
//! ellipsoid 2.5° and 6.6 mm at the object's centre). We ask for 3° and 1 cm: a wrong grid
//! candidate or a flipped symmetric object is off by ≥ 15° (or 180°), far outside.

use glam::{Quat, Vec3};
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::Rigid;
use lightfuse::spatial::KdTree;
use lightfuse::stages::reconstruct::init::PointCloud;
use lightfuse::stages::reconstruct::register::*;

fn brute<const K: usize>(pts: &[[f32; K]], q: &[f32; K]) -> (usize, f32) {
    let mut best = (usize::MAX, f32::INFINITY);
    for (i, p) in pts.iter().enumerate() {
        let d2: f32 = (0..K).map(|d| (p[d] - q[d]) * (p[d] - q[d])).sum();
        if d2 < best.1 {
            best = (i, d2);
        }
    }
    best
}

fn check_tree<const K: usize>(seed: u64, n: usize) {
    let mut rng = SplitMix(seed);
    let mut pts: Vec<[f32; K]> = (0..n)
        .map(|_| std::array::from_fn(|_| rng.range(-1.0, 1.0)))
        .collect();
    // Duplicates and a degenerate (flat) cluster.
    for i in 0..n / 10 {
        pts.push(pts[i]);
        pts.push(std::array::from_fn(|d| {
            if d == 0 {
                0.5
            } else {
                i as f32 * 1e-3
            }
        }));
    }
    let tree = KdTree::new(&pts);
    for _ in 0..500 {
        let q: [f32; K] = std::array::from_fn(|_| rng.range(-1.3, 1.3));
        let (i, d2) = tree.nearest(&q).unwrap();
        let (_, bd2) = brute(&pts, &q);
        // Ties (duplicates) may return another index with the same distance.
        assert_eq!(d2, bd2);
        let e: f32 = (0..K).map(|d| (pts[i][d] - q[d]).powi(2)).sum();
        assert_eq!(e, d2);
        let r2 = bd2 * 1.5;
        assert!(tree.nearest_within(&q, r2).is_some());
        assert!(tree.nearest_within(&q, bd2).is_none(), "strictly closer");
        // `within`: the same set as a scan of every point, at radii holding a few to hundreds
        // (duplicates and the points on a split plane included).
        for r2 in [bd2 * 1.5, 0.01, 0.05] {
            let mut got = Vec::new();
            tree.within(&q, r2, &mut got);
            got.sort_by_key(|&(i, _)| i);
            let want: Vec<(usize, f32)> = pts
                .iter()
                .enumerate()
                .map(|(i, p)| (i, (0..K).map(|d| (p[d] - q[d]).powi(2)).sum::<f32>()))
                .filter(|&(_, d2)| d2 < r2)
                .collect();
            assert_eq!(got, want, "within √{r2}");
        }
    }
}

#[test]
fn kd_tree_matches_brute_force() {
    check_tree::<3>(1, 3000);
    check_tree::<6>(2, 3000);
    check_tree::<3>(3, 5); // a single leaf
    assert!(KdTree::<3>::new(&[]).nearest(&[0.0; 3]).is_none());
}

#[test]
fn rotation_grid_covers_so3() {
    let step = 15.0f32;
    let grid = rotation_grid(step);
    assert!(grid.contains(&Quat::IDENTITY));
    let mut rng = SplitMix(5);
    let mut worst = 0.0f32;
    for _ in 0..2000 {
        let q = Quat::from_array(rng.unit_quat());
        let d = grid
            .iter()
            .map(|g| g.angle_between(q))
            .fold(f32::INFINITY, f32::min);
        worst = worst.max(d);
    }
    // Up axis within ~step/√2 of a grid axis (cap spacing) and the turn within step/2:
    // together at most ~step. The ICP basin is wider than that.
    assert!(
        worst.to_degrees() < step,
        "covering radius {}°",
        worst.to_degrees()
    );
}

/// A smooth colour field in the object's frame with features ~4–8 cm across: distinct
/// frequencies per channel so that no rotation maps it onto itself.
fn texture(p: Vec3) -> [f32; 3] {
    let f = |k: Vec3, phase: f32| 0.5 + 0.35 * (k.dot(p) + phase).sin();
    [
        f(Vec3::new(31.0, 9.0, -17.0), 0.3),
        f(Vec3::new(-12.0, 27.0, 21.0), 1.1),
        f(Vec3::new(19.0, -23.0, 29.0), 2.0),
    ]
}

#[derive(Clone, Copy, Debug)]
enum Shape {
    /// Radius 0.15 m: only the texture fixes the rotation.
    Ball,
    /// Surface of revolution about +Y (a vase, radius 0.06–0.12 m over 0.35 m).
    Vase,
    /// An ellipsoid 0.2 × 0.1 × 0.07 m (semi-axes).
    Ellipsoid,
    /// A plain (one-colour) square tin, 0.14 × 0.2 × 0.14 m: four-fold about +Y and the same
    /// upside down, so only its translation is defined.
    Tin,
}

/// Point and outward normal at parameters (a, b) ∈ [0, 1)², object frame (base at y = 0).
fn surface(shape: Shape, a: f32, b: f32) -> (Vec3, Vec3) {
    let phi = a * std::f32::consts::TAU;
    match shape {
        Shape::Ball => {
            let y = 1.0 - 2.0 * b;
            let r = (1.0 - y * y).sqrt();
            let n = Vec3::new(r * phi.cos(), y, r * phi.sin());
            (n * 0.15 + Vec3::new(0.0, 0.15, 0.0), n)
        }
        Shape::Vase => {
            let y = 0.35 * b;
            let rad = |y: f32| 0.09 + 0.03 * (y * 18.0).sin();
            let dr = 0.03 * 18.0 * (y * 18.0).cos();
            let radial = Vec3::new(phi.cos(), 0.0, phi.sin());
            let n = (radial - Vec3::Y * dr).normalize();
            (radial * rad(y) + Vec3::Y * y, n)
        }
        Shape::Ellipsoid => {
            let y = 1.0 - 2.0 * b;
            let r = (1.0 - y * y).sqrt();
            let u = Vec3::new(r * phi.cos(), y, r * phi.sin());
            let ax = Vec3::new(0.2, 0.07, 0.1);
            ((u * ax) + Vec3::new(0.0, 0.07, 0.0), (u / ax).normalize())
        }
        Shape::Tin => {
            // a picks the face (six equal sixths) and one coordinate on it, b the other.
            let f = ((a * 6.0) as usize).min(5);
            let u = a * 6.0 - f as f32;
            let (axis, sign) = (f / 2, if f % 2 == 0 { 1.0 } else { -1.0 });
            let half = Vec3::new(0.07, 0.1, 0.07);
            let mut p = Vec3::ZERO;
            let mut n = Vec3::ZERO;
            p[axis] = sign * half[axis];
            n[axis] = sign;
            let (i, j) = ((axis + 1) % 3, (axis + 2) % 3);
            p[i] = (2.0 * u - 1.0) * half[i];
            p[j] = (2.0 * b - 1.0) * half[j];
            (p + Vec3::new(0.0, 0.1, 0.0), n)
        }
    }
}

/// The capture's noise along the normal: uniform with σ ≈ 0.58 mm, at most 1.7 mm.
fn normal_noise(rng: &mut SplitMix) -> f32 {
    (rng.f32() - 0.5) * 0.002 * 3f32.sqrt()
}

/// Points of `shape` seen from roughly direction `view` (object frame): the surface facing it
/// (n·view > −0.2), sampled afresh with `seed` at ~`spacing`, 1 mm noise along the normal, lit
/// by `light` (brightness ∝ 0.4 + 0.6 max(0, n·light), times `gain`), placed by `pose`.
fn observe(
    shape: Shape,
    view: Vec3,
    light: Vec3,
    gain: f32,
    pose: &Rigid,
    seed: u64,
) -> PointCloud {
    let mut rng = SplitMix(seed);
    let mut c = PointCloud::default();
    let area = match shape {
        Shape::Ball => 4.0 * std::f32::consts::PI * 0.15 * 0.15,
        Shape::Vase => std::f32::consts::TAU * 0.09 * 0.35,
        Shape::Ellipsoid => 0.2,
        Shape::Tin => 4.0 * 0.14 * 0.2 + 2.0 * 0.14 * 0.14,
    };
    let spacing = 0.006;
    let n = (area / (spacing * spacing)) as usize;
    let q = pose.quat();
    for _ in 0..n {
        let (p, nrm) = surface(shape, rng.f32(), rng.f32());
        if nrm.dot(view.normalize()) < -0.2 {
            continue;
        }
        let p = p + nrm * normal_noise(&mut rng);
        let shade = gain * (0.4 + 0.6 * nrm.dot(light.normalize()).max(0.0));
        let albedo = match shape {
            Shape::Tin => [0.42, 0.74, 0.62],
            _ => texture(p),
        };
        let rgb = albedo.map(|x| x * shade);
        c.push(
            (q * p + Vec3::from_array(pose.translation)).to_array(),
            (q * nrm).to_array(),
            rgb,
            1,
            0,
            0.004,
        );
    }
    c
}

fn random_pose(rng: &mut SplitMix, full_rotation: bool) -> Rigid {
    let q = if full_rotation {
        Quat::from_array(rng.unit_quat())
    } else {
        Quat::from_rotation_y(rng.range(0.0, std::f32::consts::TAU))
    };
    let dir = Vec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-0.3, 0.3),
        rng.range(-1.0, 1.0),
    )
    .normalize();
    Rigid {
        rotation: q.to_array(),
        translation: (dir * 0.5).to_array(),
    }
}

fn errors(est: &Rigid, truth: &Rigid) -> (f32, f32) {
    let rot = est.quat().angle_between(truth.quat()).to_degrees();
    // Displacement error at the object's centre (~0.15 m above its base).
    let c = [0.0, 0.12, 0.0];
    let (a, b) = (est.transform_point(c), truth.transform_point(c));
    let t = (0..3).map(|d| (a[d] - b[d]).powi(2)).sum::<f32>().sqrt();
    (rot, t)
}

fn recover(shape: Shape, full_rotation: bool, seed: u64) {
    let (src, tgt, truth) = pair(shape, full_rotation, seed);
    let reg = register(&src, &tgt, &RegisterOptions::default()).expect("enough points");
    let (rot, t) = errors(&reg.transform, &truth);
    // The truth must not score better than the estimate by much: the search found the basin.
    let at_truth = evaluate(&src, &tgt, &truth, &RegisterOptions::default()).unwrap();
    eprintln!(
        "score at truth {:.3}, estimate {:.3}",
        at_truth.score, reg.score
    );
    eprintln!(
        "seed {seed}: rot {rot:.3}°, trans {:.2} mm, fitness {:.2}, rmse {:.4}",
        t * 1e3,
        reg.fitness,
        reg.rmse
    );
    assert!(rot < 3.0, "rotation off by {rot}° (seed {seed})");
    assert!(t < 0.01, "translation off by {t} m (seed {seed})");
    assert!(reg.fitness > 0.3 && reg.rmse < 0.003);
}

#[test]
fn registers_a_textured_ball_by_its_texture() {
    for seed in [10, 20, 30] {
        recover(Shape::Ball, false, seed);
    }
    recover(Shape::Ball, true, 40);
}

#[test]
fn registers_a_textured_vase() {
    recover(Shape::Vase, false, 11);
}

/// Known failure, left visible: with seed 21 the two views of the vase overlap little (the
/// true pose has fitness ~0.35) and a turned pose that overlaps more scores better; the
/// estimate is off by ~110°. Run with `--ignored` when working on the score.
#[test]
#[ignore = "known failure: symmetric shape with little overlap (see the doc comment)"]
fn registers_a_textured_vase_with_little_overlap() {
    recover(Shape::Vase, false, 21);
}

#[test]
fn registers_an_ellipsoid_under_any_rotation() {
    for seed in [12, 22] {
        recover(Shape::Ellipsoid, true, seed);
    }
}

#[test]
fn registration_is_deterministic_and_refuses_empty_clouds() {
    let src = observe(Shape::Vase, Vec3::X, Vec3::Y, 1.0, &Rigid::IDENTITY, 1);
    let pose = random_pose(&mut SplitMix(3), false);
    let tgt = observe(Shape::Vase, Vec3::Z, Vec3::Y, 1.0, &pose, 2);
    let opts = RegisterOptions::default();
    assert_eq!(register(&src, &tgt, &opts), register(&src, &tgt, &opts));
    assert!(register(&src, &PointCloud::default(), &opts).is_none());
}

/// Two observations of `shape` and the true pose between them (any rotation when
/// `full_rotation`, else about the vertical): the reference seen from +X+Z, state k from −X
/// (about half the surface in common), other sample positions, other light and exposure.
fn pair(shape: Shape, full_rotation: bool, seed: u64) -> (PointCloud, PointCloud, Rigid) {
    let mut rng = SplitMix(seed);
    let truth = random_pose(&mut rng, full_rotation);
    let src = observe(
        shape,
        Vec3::new(1.0, 0.5, 0.6),
        Vec3::new(0.3, 1.0, 0.2),
        1.0,
        &Rigid::IDENTITY,
        seed + 1,
    );
    let view_k = truth.quat().inverse() * Vec3::new(-1.0, 0.6, 0.4);
    let tgt = observe(
        shape,
        view_k,
        Vec3::new(-0.5, 1.0, -0.4),
        0.6,
        &truth,
        seed + 2,
    );
    (src, tgt, truth)
}

/// `truth` moved by `deg` about a fixed tilted axis and by `cm` along another, so the start
/// is off in every parameter.
fn perturbed(truth: &Rigid, deg: f32, cm: f32) -> Rigid {
    let dq = Quat::from_axis_angle(Vec3::new(0.3, 1.0, -0.5).normalize(), deg.to_radians());
    let dt = Vec3::new(0.6, -0.2, 0.77).normalize() * cm / 100.0;
    Rigid {
        rotation: (dq * truth.quat()).normalize().to_array(),
        translation: (Vec3::from_array(truth.translation) + dt).to_array(),
    }
}

/// Choosing between basins ([`Pair::best_fit`], what stage 1 does between the rendered alignment's
/// polished pose and registration's): the hypothesis near the truth wins against one 60° off
/// (in either order), and colour has no say: with the target's colours replaced by noise (a
/// chrome object's reflections under another light are no better) the choice and its cost
/// are the same to the bit, while the trimmed score, which weighs colour, changes.
#[test]
fn best_fit_picks_the_basin_by_geometry_alone() {
    let opts = RegisterOptions::default();
    for (shape, seed) in [(Shape::Ball, 10), (Shape::Vase, 11), (Shape::Ellipsoid, 12)] {
        let (src, tgt, truth) = pair(shape, false, seed);
        let clouds = Pair::new(&src, &tgt, &opts).expect("enough points");
        let near = clouds
            .polish(&[perturbed(&truth, 3.0, 0.5)], &PolishLimits::default())
            .expect("near start")
            .transform;
        let far = perturbed(&truth, 60.0, 1.5);
        let (k, fit) = clouds.best_fit(&[far, near]).expect("two hypotheses");
        assert_eq!(k, 1, "{shape:?}: picked the far hypothesis");
        let (k2, _) = clouds.best_fit(&[near, far]).unwrap();
        assert_eq!(k2, 0, "{shape:?}: order matters");
        let at_far = clouds.evaluate(&far);
        assert_eq!(Some(at_far), evaluate(&src, &tgt, &far, &opts));
        eprintln!(
            "{shape:?}: geometric cost near {:.4}, 60° off {:.4}",
            fit.geometric_cost, at_far.geometric_cost
        );
        assert!(fit.geometric_cost >= 0.0 && fit.geometric_cost < at_far.geometric_cost);
        let mut noisy = tgt.clone();
        let mut rng = SplitMix(seed + 7);
        for c in &mut noisy.rgb {
            *c = [
                rng.range(0.01, 1.0),
                rng.range(0.01, 1.0),
                rng.range(0.01, 1.0),
            ];
        }
        let (k3, fit3) = Pair::new(&src, &noisy, &opts)
            .unwrap()
            .best_fit(&[far, near])
            .unwrap();
        assert_eq!((k3, fit3.geometric_cost), (1, fit.geometric_cost));
        assert_ne!(
            fit3.score, fit.score,
            "{shape:?}: the colours did not change the score"
        );
    }
    let none = PointCloud::default();
    assert!(Pair::new(&none, &none, &opts).is_none());
    let (src, tgt, _) = pair(Shape::Ball, false, 10);
    assert!(Pair::new(&src, &tgt, &opts)
        .unwrap()
        .best_fit(&[])
        .is_none());
}

/// The polish (ICP from a rough pose, as stage 1 applies to the rendered alignment's) brings a
/// start 5° and 1.5 cm off (the alignment's errors on bedroom: up to 5.7° and 2 cm) to the
/// clouds' fixed point, within [`recover`]'s 3° and 1 cm (its header says why), and closer
/// than it started; a start 60° off is outside the basin the polish may search: refused.
#[test]
fn polish_refines_a_rough_pose_and_refuses_a_far_one() {
    let opts = RegisterOptions::default();
    let limits = PolishLimits::default();
    for (shape, seed) in [(Shape::Ball, 10), (Shape::Vase, 11), (Shape::Ellipsoid, 12)] {
        let (src, tgt, truth) = pair(shape, false, seed);
        let start = perturbed(&truth, 5.0, 1.5);
        let (r0, t0) = errors(&start, &truth);
        let clouds = Pair::new(&src, &tgt, &opts).expect("enough points");
        let out = clouds
            .polish(&[start], &limits)
            .expect("a near start is polished");
        let (rot, t) = errors(&out.transform, &truth);
        eprintln!(
            "{shape:?} seed {seed}: start {r0:.2}° {:.1} mm -> {rot:.2}° {:.1} mm",
            t0 * 1e3,
            t * 1e3
        );
        assert!(rot < 3.0 && t < 0.01, "{shape:?}: {rot}° {t} m");
        assert!(rot < r0 && t < t0, "{shape:?}: no closer than the start");
        let far = perturbed(&truth, 60.0, 1.5);
        assert!(
            clouds.polish(&[far], &limits).is_none(),
            "{shape:?}: far start"
        );
        // A second start beyond the limits of the first is not tried.
        let both = clouds.polish(&[start, far], &limits).expect("the near one");
        assert_eq!(both, out);
    }
    let (src, tgt, _) = pair(Shape::Ball, false, 10);
    assert!(Pair::new(&src, &tgt, &opts)
        .unwrap()
        .polish(&[], &limits)
        .is_none());
}

/// A plain four-fold tin under a change of lighting, each state seen from all around and
/// above (as a dataset's state is: every side and the top): no image fixes which quarter turn
/// (or flip) it made, so registration may return any of its eight symmetric rotations, but the
/// translation of its centre (where every symmetry axis passes) must be right: it is what
/// moves the shadow. Within 1° of one symmetric rotation and 5 mm at the centre, for
/// registration and for the polish from a start 5° and 1.5 cm off. (Seen from two sides only,
/// as in [`recover`], the score is flat along a slide of the faces and the polish can slide
/// with it: seed 33 ended 12° off, scoring as well as the truth.)
#[test]
fn a_four_fold_tin_gets_its_translation_whatever_turn_is_chosen() {
    let opts = RegisterOptions::default();
    let centre = Vec3::new(0.0, 0.1, 0.0);
    for seed in [13, 23, 33] {
        let truth = random_pose(&mut SplitMix(seed), false);
        let up = Vec3::Y; // the truth turns about +Y only: "above" is the same in both frames
        let src = observe(
            Shape::Tin,
            up,
            Vec3::new(0.3, 1.0, 0.2),
            1.0,
            &Rigid::IDENTITY,
            seed + 1,
        );
        let tgt = observe(
            Shape::Tin,
            up,
            Vec3::new(-0.5, 1.0, -0.4),
            0.6,
            &truth,
            seed + 2,
        );
        let clouds = Pair::new(&src, &tgt, &opts).expect("enough points");
        let reg = clouds.register();
        assert_eq!(Some(reg), register(&src, &tgt, &opts));
        let start = perturbed(&truth, 5.0, 1.5);
        let polished = clouds
            .polish(&[start], &PolishLimits::default())
            .expect("a near start is polished");
        for (what, est) in [
            ("registered", reg.transform),
            ("polished", polished.transform),
        ] {
            // The least angle to truth · S over the tin's eight symmetries S (about its centre).
            let flips = [Quat::IDENTITY, Quat::from_rotation_x(std::f32::consts::PI)];
            let rot = (0..4)
                .flat_map(|k| {
                    flips.map(|f| Quat::from_rotation_y(k as f32 * std::f32::consts::FRAC_PI_2) * f)
                })
                .map(|s| est.quat().angle_between(truth.quat() * s).to_degrees())
                .fold(f32::INFINITY, f32::min);
            let at = |r: &Rigid| Vec3::from_array(r.transform_point(centre.to_array()));
            let t = (at(&est) - at(&truth)).length();
            eprintln!(
                "tin seed {seed} {what}: {rot:.2}° from a symmetric turn, {:.2} mm at the centre",
                t * 1e3
            );
            assert!(rot < 1.0 && t < 0.005, "seed {seed} {what}: {rot}°, {t} m");
        }
    }
}

/// Registration under a strong change of lighting, each state seen from all around and above
/// as a dataset's is: the light from opposite sides, a third of the exposure, and a warm
/// against a cool tint (log chromaticity cancels a per-channel gain; shading is what remains).
/// Seen this way the textured shapes are pinned to 1° and 5 mm at their centre (issue 15's
/// figure; [`recover`]'s 3° and 1 cm are for two half views).
#[test]
fn registers_under_a_strong_lighting_change_to_one_degree_and_five_mm() {
    let opts = RegisterOptions::default();
    for (shape, seed) in [(Shape::Ball, 14), (Shape::Vase, 24), (Shape::Ellipsoid, 34)] {
        let truth = random_pose(&mut SplitMix(seed), false);
        let up = Vec3::Y;
        let tint = |mut c: PointCloud, k: [f32; 3]| {
            for p in &mut c.rgb {
                *p = [p[0] * k[0], p[1] * k[1], p[2] * k[2]];
            }
            c
        };
        let src = tint(
            observe(
                shape,
                up,
                Vec3::new(1.0, 0.4, 0.2),
                1.0,
                &Rigid::IDENTITY,
                seed + 1,
            ),
            [1.2, 1.0, 0.7],
        );
        let tgt = tint(
            observe(
                shape,
                up,
                Vec3::new(-1.0, 0.3, -0.3),
                0.33,
                &truth,
                seed + 2,
            ),
            [0.7, 0.9, 1.3],
        );
        let reg = register(&src, &tgt, &opts).expect("enough points");
        let (rot, t) = errors(&reg.transform, &truth);
        eprintln!("{shape:?} seed {seed}: {rot:.2}°, {:.2} mm", t * 1e3);
        assert!(
            rot < 1.0 && t < 0.005,
            "{shape:?} seed {seed}: {rot}°, {t} m"
        );
    }
}

/// A plain steel pot, the demo's kind of object: a cylinder (radius 0.1 m, 0.15 m tall, with a
/// lid) and two handles (3 × 4 × 3 cm blocks on opposite sides), seen from all around and above
/// with ~6 mm between points and 1 mm noise along the normal. Only the handles fix its turn
/// about +Y. Steel grey everywhere but for a blue reflection of the sky on the body, the points
/// within 20° of azimuth `glint` (object frame, measured as a turn about +Y): where it sits is
/// the lighting's doing, not the object's.
fn observe_pot(glint: f32, pose: &Rigid, seed: u64) -> PointCloud {
    let mut rng = SplitMix(seed);
    let mut c = PointCloud::default();
    let (r, h, spacing) = (0.1f32, 0.15f32, 0.006f32);
    let q = pose.quat();
    let mut put = |p: Vec3, n: Vec3, rgb: [f32; 3], rng: &mut SplitMix| {
        let p = p + n * normal_noise(rng);
        c.push(
            (q * p + Vec3::from_array(pose.translation)).to_array(),
            (q * n).to_array(),
            rgb,
            1,
            0,
            0.004,
        );
    };
    let steel = [0.55, 0.55, 0.58];
    let sky = [0.3, 0.42, 0.85];
    let wall = std::f32::consts::TAU * r * h;
    for _ in 0..(wall / (spacing * spacing)) as usize {
        let (phi, y) = (rng.f32() * std::f32::consts::TAU, rng.f32() * h);
        // A turn by φ about +Y takes +X to (cos φ, 0, −sin φ).
        let n = Vec3::new(phi.cos(), 0.0, -phi.sin());
        let d = (phi - glint + std::f32::consts::PI).rem_euclid(std::f32::consts::TAU)
            - std::f32::consts::PI;
        let rgb = if d.abs() < 20f32.to_radians() {
            sky
        } else {
            steel
        };
        put(n * r + Vec3::Y * y, n, rgb, &mut rng);
    }
    let lid = std::f32::consts::PI * r * r;
    for _ in 0..(lid / (spacing * spacing)) as usize {
        let (phi, s) = (rng.f32() * std::f32::consts::TAU, r * rng.f32().sqrt());
        put(
            Vec3::new(s * phi.cos(), h, s * phi.sin()),
            Vec3::Y,
            steel,
            &mut rng,
        );
    }
    // Each handle: the block x ∈ [r, r + 3 cm], y ∈ [8, 12] cm, z ∈ ±1.5 cm (mirrored in x for
    // the other), its five faces off the body sampled by area.
    let (lo, hi) = (Vec3::new(r, 0.08, -0.015), Vec3::new(r + 0.03, 0.12, 0.015));
    for side in [1.0f32, -1.0] {
        for (axis, at_max) in [(0, true), (1, false), (1, true), (2, false), (2, true)] {
            let (i, j) = ((axis + 1) % 3, (axis + 2) % 3);
            let area = (hi[i] - lo[i]) * (hi[j] - lo[j]);
            for _ in 0..(area / (spacing * spacing)).ceil() as usize {
                let mut p = Vec3::ZERO;
                let mut n = Vec3::ZERO;
                p[axis] = if at_max { hi[axis] } else { lo[axis] };
                n[axis] = if at_max { 1.0 } else { -1.0 };
                p[i] = lo[i] + rng.f32() * (hi[i] - lo[i]);
                p[j] = lo[j] + rng.f32() * (hi[j] - lo[j]);
                let mirror = Vec3::new(side, 1.0, 1.0);
                put(p * mirror, n * mirror, steel, &mut rng);
            }
        }
    }
    c
}

/// The polish chooses by geometry, not by the colour-aware score. The pot's reflection sits 8°
/// further round its body in state k than in the reference, so the pose turned 8° about its
/// axis lays reflection on reflection: the trimmed score (colour included) prefers it to the
/// truth, while the handles make it fit worse in geometry. Polished from the rendered
/// alignment's kind of start (1.5° and 1 cm off) with that turned pose as the second start
/// (registration's estimate, as stage 1 passes it), the result must be the handles' answer:
/// within 1.5° and 5 mm of the truth at the base. (Choosing by the score, as the polish once
/// did, returns the turned pose, 8° off, as it did the demo's pot at 5.6°.) 1.5°: ICP's
/// fixed point from a rough start stops short of the truth by up to ~1° on shapes pinned by a
/// small feature (the demo's pot: 1.6° from its true pose).
#[test]
fn polish_follows_the_geometry_where_a_reflection_moved() {
    let opts = RegisterOptions::default();
    let glint = 8f32.to_radians();
    for (seed, turn) in [(15u64, 0.7f32), (25, -2.1)] {
        let truth = Rigid {
            rotation: Quat::from_rotation_y(turn).to_array(),
            translation: [0.35, 0.0, -0.2],
        };
        let src = observe_pot(0.0, &Rigid::IDENTITY, seed + 1);
        let tgt = observe_pot(glint, &truth, seed + 2);
        let clouds = Pair::new(&src, &tgt, &opts).expect("enough points");
        let turned = Rigid {
            rotation: (truth.quat() * Quat::from_rotation_y(glint)).to_array(),
            translation: truth.translation,
        };
        let (at_truth, at_turned) = (clouds.evaluate(&truth), clouds.evaluate(&turned));
        eprintln!(
            "pot seed {seed}: score {:.3} at the truth, {:.3} turned; geometric cost {:.5}, {:.5}",
            at_truth.score, at_turned.score, at_truth.geometric_cost, at_turned.geometric_cost
        );
        // The case this test is about: colour misleads, geometry does not.
        assert!(
            at_turned.score < at_truth.score,
            "seed {seed}: colour agrees"
        );
        assert!(at_turned.geometric_cost > at_truth.geometric_cost);
        let start = perturbed(&truth, 1.5, 1.0);
        let out = clouds
            .polish(&[start, turned], &PolishLimits::default())
            .expect("both starts are near");
        let rot = out
            .transform
            .quat()
            .angle_between(truth.quat())
            .to_degrees();
        let at = |r: &Rigid| Vec3::from_array(r.transform_point([0.0; 3]));
        let t = (at(&out.transform) - at(&truth)).length();
        eprintln!("pot seed {seed}: polished {rot:.2}°, {:.2} mm", t * 1e3);
        assert!(rot < 1.5 && t < 0.005, "seed {seed}: {rot}°, {t} m");
    }
}

/// `truth` turned by `deg` about the object's own axis (+Y of its frame, through its origin):
/// for a solid of revolution the same surface, its texture turned.
fn turned_about_axis(truth: &Rigid, deg: f32) -> Rigid {
    truth.compose(&Rigid {
        rotation: Quat::from_rotation_y(deg.to_radians()).to_array(),
        translation: [0.0; 3],
    })
}

/// As [`pair`], but each state seen all round (two opposite views, as a state's many cameras
/// see an object): the turned poses of a solid of revolution then fit as well as the truth.
fn all_round_pair(shape: Shape, seed: u64) -> (PointCloud, PointCloud, Rigid) {
    let mut rng = SplitMix(seed);
    let truth = random_pose(&mut rng, false);
    let light = |s: f32| Vec3::new(0.3 * s, 1.0, 0.2);
    let mut src = PointCloud::default();
    let mut tgt = PointCloud::default();
    for (k, v) in [Vec3::new(1.0, 0.5, 0.6), Vec3::new(-1.0, 0.5, -0.6)]
        .iter()
        .enumerate()
    {
        let k = k as u64;
        src.extend(&observe(
            shape,
            *v,
            light(1.0),
            1.0,
            &Rigid::IDENTITY,
            seed + 1 + 10 * k,
        ));
        tgt.extend(&observe(
            shape,
            *v,
            Vec3::new(-0.5, 1.0, -0.4),
            0.6,
            &truth,
            seed + 2 + 10 * k,
        ));
    }
    (src, tgt, truth)
}

/// A cloud's colours with the texture taken out (`pose` placed it): each point's albedo
/// replaced by one grey, its shading kept (a plain solid of revolution, which no turn changes).
fn plain(cloud: &PointCloud, pose: &Rigid) -> PointCloud {
    let inv = pose.inverse();
    let mut c = cloud.clone();
    for (rgb, p) in c.rgb.iter_mut().zip(&cloud.position) {
        let a = texture(Vec3::from_array(inv.transform_point(*p)));
        *rgb = std::array::from_fn(|d| rgb[d] / a[d] * 0.5);
    }
    c
}

/// The texture's verdict where geometry ties ([`Pair::shading_residual`]): the textured vase,
/// seen all round and lit from elsewhere with another gain in each state, carried by the true
/// pose leaves a log ratio the order-2 shading model explains (residual measured 0.075: the
/// model's error on 0.4 + 0.6 max(0, n·l), whose kink it cannot follow), and turned about its
/// axis by a quarter or a half turn (the same surface: geometric costs within 0.01) one it
/// cannot (measured 0.40-0.41): we ask for a factor 2. A per-channel gain on the target
/// (exposure, the light's colour) is the model's constant term: the residual is unchanged
/// (1e-4, float rounding). Without the texture the residual still depends on the turn a
/// little, through where the two lights' kinks fall (measured 0.039-0.071 against 0.052 at the
/// truth): the texture's signal must be five times that.
#[test]
fn shading_residual_sees_the_texture_turned_and_not_the_light() {
    let opts = RegisterOptions::default();
    for seed in [11, 21, 31] {
        let (src, tgt, truth) = all_round_pair(Shape::Vase, seed);
        let clouds = Pair::new(&src, &tgt, &opts).unwrap();
        let at_truth = clouds.shading_residual(&truth).expect("overlap");
        let mut tinted = tgt.clone();
        for c in &mut tinted.rgb {
            *c = [c[0] * 1.7, c[1] * 0.6, c[2] * 1.1];
        }
        let at_tinted = Pair::new(&src, &tinted, &opts)
            .unwrap()
            .shading_residual(&truth)
            .unwrap();
        let untextured =
            Pair::new(&plain(&src, &Rigid::IDENTITY), &plain(&tgt, &truth), &opts).unwrap();
        let plain_truth = untextured.shading_residual(&truth).unwrap();
        for deg in [90.0, 180.0] {
            let turned = turned_about_axis(&truth, deg);
            let (g0, g1) = (clouds.evaluate(&truth), clouds.evaluate(&turned));
            let wrong = clouds.shading_residual(&turned).unwrap();
            let plain_turned = untextured.shading_residual(&turned).unwrap();
            eprintln!(
                "seed {seed}, {deg}°: cost {:.4} / {:.4}; shading {at_truth:.4} / {wrong:.4} (tinted {at_tinted:.4}); plain {plain_truth:.4} / {plain_turned:.4}",
                g0.geometric_cost, g1.geometric_cost
            );
            assert!((g0.geometric_cost - g1.geometric_cost).abs() < 0.01);
            assert!(wrong > 2.0 * at_truth, "seed {seed}, {deg}°");
            assert!(
                wrong - at_truth > 5.0 * (plain_turned - plain_truth).abs(),
                "seed {seed}, {deg}°: the texture's signal is not above the model's error"
            );
        }
        assert!(
            (at_tinted - at_truth).abs() < 1e-4,
            "{at_tinted} vs {at_truth}"
        );
    }
}

/// [`Pair::choose_turn`]: the textured vase given turned by 120° about its axis (geometry
/// ties, so registration could have chosen it) comes back to the truth within [`recover`]'s
/// 3° and 1 cm, from a turn of 240°; the plain vase, which any turn about its axis leaves the
/// same, keeps its axis and its place on it (3°, 1 cm), whatever turn it takes; the ellipsoid
/// (the same after a half turn about its vertical axis, not after a quarter) given 150° off
/// goes to the basin that fits and the half turn its texture says, within 3° and 1 cm, and so
/// it does from 20 cm away as well. Deterministic.
#[test]
fn choose_turn_lets_the_texture_decide_between_geometric_ties() {
    let opts = RegisterOptions::default();
    let limits = PolishLimits::default();
    let turn = TurnOptions::default();
    for seed in [11, 21] {
        let (src, tgt, truth) = all_round_pair(Shape::Vase, seed);
        let given = turned_about_axis(&truth, 120.0);
        let clouds = Pair::new(&src, &tgt, &opts).unwrap();
        let choice = clouds.choose_turn(&given, Vec3::Y, &limits, &turn);
        let (rot, t) = errors(&choice.transform, &truth);
        eprintln!(
            "vase seed {seed}: turn {}°, {} ties, {rot:.2}°, {:.2} mm",
            choice.turn_deg,
            choice.ties,
            t * 1e3
        );
        assert!(
            choice.ties >= 12,
            "a solid of revolution ties at most turns"
        );
        assert!(rot < 3.0 && t < 0.01, "seed {seed}: {rot}°, {t} m");
        assert_eq!(choice, clouds.choose_turn(&given, Vec3::Y, &limits, &turn));

        let untextured =
            Pair::new(&plain(&src, &Rigid::IDENTITY), &plain(&tgt, &truth), &opts).unwrap();
        let plain_choice = untextured.choose_turn(&given, Vec3::Y, &limits, &turn);
        let tilt = (plain_choice.transform.quat() * Vec3::Y).angle_between(truth.quat() * Vec3::Y);
        let (_, t) = errors(&plain_choice.transform, &truth);
        eprintln!(
            "plain vase seed {seed}: turn {}°, tilt {:.2}°, {:.2} mm on the axis",
            plain_choice.turn_deg,
            tilt.to_degrees(),
            t * 1e3
        );
        assert!(
            tilt.to_degrees() < 3.0 && t < 0.01,
            "seed {seed}: plain vase"
        );
    }
    let (src, tgt, truth) = all_round_pair(Shape::Ellipsoid, 12);
    let given = turned_about_axis(&truth, 150.0);
    let choice = Pair::new(&src, &tgt, &opts)
        .unwrap()
        .choose_turn(&given, Vec3::Y, &limits, &turn);
    let (rot, t) = errors(&choice.transform, &truth);
    eprintln!(
        "ellipsoid: turn {}°, {} ties, {rot:.2}°, {:.2} mm",
        choice.turn_deg,
        choice.ties,
        t * 1e3
    );
    assert!(rot < 3.0 && t < 0.01, "ellipsoid: {rot}°, {t} m");
    // Lost in place too (20 cm off, more than the polish may move it): the translation fitted
    // afresh to the turned rotation finds it.
    let mut lost = given;
    lost.translation[0] += 0.2;
    let choice = Pair::new(&src, &tgt, &opts)
        .unwrap()
        .choose_turn(&lost, Vec3::Y, &limits, &turn);
    let (rot, t) = errors(&choice.transform, &truth);
    eprintln!(
        "ellipsoid 20 cm off: turn {}°, {rot:.2}°, {:.2} mm",
        choice.turn_deg,
        t * 1e3
    );
    assert!(rot < 3.0 && t < 0.01, "ellipsoid 20 cm off: {rot}°, {t} m");
}
