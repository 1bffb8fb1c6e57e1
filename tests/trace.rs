//! The tracing core against its brute-force f64 reference (`trace::reference`), and the cases
//! the reference cannot reach by chance: batch boundaries, ties, early exit, degenerate rays.
//!
//! Tolerances. The fast path works in f32 in each component's frame; the reference in f64 in
//! the world. A hit's t, ξ and α_eff then agree to a few ulps relative to the scene's size
//! (~4 m here), i.e. ~1e-6; the transmittance in front of a hit is a product of up to a few
//! hundred factors 1 − α with α ≤ 0.99, whose relative error grows to ~1e-4 at worst. Weighted
//! sums (Σw = alpha ≤ 1, times values ≤ ~8 for depth) therefore agree to well under 1e-3·scale,
//! which is what [`close`] allows. The one way the two can legitimately differ more is a pair of
//! hits whose t differ by less than f32 resolution, composited in different orders; random
//! scenes make that vanishingly rare, and the tie tests below construct exact ties on purpose.

use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::{Component, Rigid, Scene, Surfels};
use lightfuse::trace::reference::{composite_brute, transmittance_brute};
use lightfuse::trace::{RayStats, SurfaceRecord, TraceScene, BATCH, MAX_OPACITY, T_MIN};

mod common;
use common::push;

fn scene_of(components: Vec<Surfels>) -> Scene {
    let mut scene = Scene::from_background(Surfels::with_sh_degree(0));
    scene.components = components
        .into_iter()
        .enumerate()
        .map(|(i, surfels)| Component {
            name: format!("c{i}"),
            id: i as u32,
            surfels,
        })
        .collect();
    scene.states[0].transforms = vec![Rigid::IDENTITY; scene.components.len()];
    scene
}

/// `n` random surfels in the cube [-1, 1]³, large enough that rays cross many of them.
fn cloud(rng: &mut SplitMix, n: usize, alpha: (f32, f32)) -> Surfels {
    let mut s = Surfels::with_sh_degree(0);
    for _ in 0..n {
        let mu = [
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        ];
        let q = rng.unit_quat();
        let scale = [rng.range(0.05, 0.25), rng.range(0.05, 0.25)];
        let a = rng.range(alpha.0, alpha.1);
        let c = rng.f32();
        push(&mut s, mu, q, scale, a, c);
    }
    s
}

fn random_rigid(rng: &mut SplitMix) -> Rigid {
    Rigid {
        rotation: rng.unit_quat(),
        translation: [
            rng.range(-0.7, 0.7),
            rng.range(-0.7, 0.7),
            rng.range(-0.7, 0.7),
        ],
    }
}

/// A ray from a sphere of radius 4 towards a random point of the central cube.
fn random_ray(rng: &mut SplitMix) -> ([f32; 3], [f32; 3]) {
    let o = glam::Vec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    )
    .normalize()
        * 4.0;
    let target = glam::Vec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    );
    (o.to_array(), (target - o).normalize().to_array())
}

fn close(what: &str, fast: &SurfaceRecord, slow: &SurfaceRecord, tol: f32) {
    let pairs = [
        ("alpha", vec![fast.alpha], vec![slow.alpha]),
        ("depth", vec![fast.depth], vec![slow.depth]),
        ("position", fast.position.to_vec(), slow.position.to_vec()),
        ("normal", fast.normal.to_vec(), slow.normal.to_vec()),
        (
            "base_color",
            fast.base_color.to_vec(),
            slow.base_color.to_vec(),
        ),
        ("metallic", vec![fast.metallic], vec![slow.metallic]),
        ("roughness", vec![fast.roughness], vec![slow.roughness]),
    ];
    for (name, a, b) in pairs {
        for (x, y) in a.iter().zip(&b) {
            assert!(
                x.is_finite() && (x - y).abs() <= tol * y.abs().max(1.0),
                "{what}: {name} fast {a:?} vs reference {b:?}\nfast {fast:?}\nref  {slow:?}"
            );
        }
    }
}

fn random_scene(seed: u64, alpha: (f32, f32), n: usize) -> (Scene, Vec<Rigid>) {
    let mut rng = SplitMix(seed);
    let scene = scene_of(vec![
        cloud(&mut rng, n, alpha),
        cloud(&mut rng, n / 2, alpha),
        Surfels::with_sh_degree(0), // an empty component must be harmless
        cloud(&mut rng, n / 2, alpha),
    ]);
    let transforms = vec![
        Rigid::IDENTITY,
        random_rigid(&mut rng),
        random_rigid(&mut rng),
        random_rigid(&mut rng),
    ];
    (scene, transforms)
}

#[test]
fn composite_matches_reference_on_random_scenes_with_moved_objects() {
    // Opaque-ish surfels end most rays within one batch; faint ones need several batches.
    for (seed, alpha, n) in [(1u64, (0.3, 1.0), 800), (2, (0.004, 0.04), 2400)] {
        let (scene, transforms) = random_scene(seed, alpha, n);
        let traced = TraceScene::new(&scene);
        let placed = traced.place(&transforms);
        let mut rng = SplitMix(seed + 100);
        let mut total_hits = 0;
        let mut max_hits = 0;
        for r in 0..150 {
            let (o, d) = random_ray(&mut rng);
            let fast = placed.composite(o, d, 0.0, f32::INFINITY);
            let slow = composite_brute(&scene, &transforms, o, d, 0.0, f32::INFINITY);
            close(&format!("seed {seed} ray {r}"), &fast, &slow, 1e-3);
            assert!(fast.hits.abs_diff(slow.hits) <= 1, "{fast:?} vs {slow:?}");
            total_hits += slow.hits;
            max_hits = max_hits.max(slow.hits);
        }
        assert!(
            total_hits > 150,
            "the scene should be hit: {total_hits} hits"
        );
        if alpha.1 < 0.5 {
            assert!(
                max_hits as usize > BATCH,
                "faint scene should need two batches or more: {max_hits} hits at most"
            );
        }
    }
}

#[test]
fn segment_bounds_are_respected() {
    let (scene, transforms) = random_scene(3, (0.1, 0.6), 600);
    let traced = TraceScene::new(&scene);
    let placed = traced.place(&transforms);
    let mut rng = SplitMix(7);
    for _ in 0..60 {
        let (o, d) = random_ray(&mut rng);
        let (t0, t1) = (rng.range(2.0, 4.0), rng.range(4.0, 6.0));
        let fast = placed.composite(o, d, t0, t1);
        let slow = composite_brute(&scene, &transforms, o, d, t0, t1);
        close("segment", &fast, &slow, 1e-3);
    }
}

#[test]
fn transmittance_matches_reference() {
    let (scene, transforms) = random_scene(4, (0.05, 0.7), 800);
    let traced = TraceScene::new(&scene);
    let placed = traced.place(&transforms);
    let mut rng = SplitMix(11);
    let (mut zero, mut partial) = (0, 0);
    for r in 0..200 {
        let (o, d) = random_ray(&mut rng);
        let t_max = rng.range(3.0, 8.0);
        let fast = placed.transmittance(o, d, 0.0, t_max) as f64;
        let slow = transmittance_brute(&scene, &transforms, o, d, 0.0, t_max);
        if fast == 0.0 {
            // Early exit: the product fell below T_MIN (up to f32 rounding of that decision).
            assert!(
                slow < T_MIN as f64 * 1.01,
                "ray {r}: early exit but T = {slow}"
            );
            zero += 1;
        } else {
            assert!(
                (fast - slow).abs() <= 2e-3 * slow + 1e-6,
                "ray {r}: {fast} vs {slow}"
            );
            partial += (slow < 0.99) as usize;
        }
    }
    assert!(
        zero > 10 && partial > 10,
        "cover both cases: {zero} {partial}"
    );
}

/// A stack of `n` parallel surfels facing +z at z = 0, −0.01, −0.02, …
fn stack(n: usize, alpha: f32, color: impl Fn(usize) -> f32) -> Surfels {
    let mut s = Surfels::with_sh_degree(0);
    for i in 0..n {
        push(
            &mut s,
            [0.0, 0.0, -0.01 * i as f32],
            [0.0, 0.0, 0.0, 1.0],
            [0.1, 0.1],
            alpha,
            color(i),
        );
    }
    s
}

#[test]
fn more_hits_than_a_batch_are_composited_in_order() {
    let n = 3 * BATCH + 5;
    // Faint enough that all are composited: 0.98^(3·128 + 5) ≈ 4e-4 > T_MIN.
    let scene = scene_of(vec![stack(n, 0.02, |i| (i % 7) as f32 / 7.0)]);
    let id = vec![Rigid::IDENTITY];
    let traced = TraceScene::new(&scene);
    let placed = traced.place(&id);
    let (o, d) = ([0.01, 0.02, 1.0], [0.0, 0.0, -1.0]);
    let fast = placed.composite(o, d, 0.0, f32::INFINITY);
    let slow = composite_brute(&scene, &id, o, d, 0.0, f32::INFINITY);
    assert_eq!(fast.hits as usize, n);
    assert_eq!(slow.hits as usize, n);
    close("stack", &fast, &slow, 1e-5);
}

#[test]
fn ray_stats_count_what_the_traversal_did() {
    // 3·BATCH + 5 faint parallel surfels on one axis: all composited (0.98^389 ≈ 4e-4 > T_MIN
    // for BATCH = 128), in four batches of at most BATCH, so four traversals of the one
    // component; a visibility ray multiplies them all in a single traversal.
    let n = 3 * BATCH + 5;
    let scene = scene_of(vec![stack(n, 0.02, |_| 0.5)]);
    let id = vec![Rigid::IDENTITY];
    let traced = TraceScene::new(&scene);
    let placed = traced.place(&id);
    let (o, d) = ([0.01, 0.02, 1.0], [0.0, 0.0, -1.0]);
    let mut stats = RayStats::default();
    let counted = placed.composite_stats(o, d, 0.0, f32::INFINITY, &mut stats);
    assert_eq!(counted, placed.composite(o, d, 0.0, f32::INFINITY));
    assert_eq!(
        (stats.rays, stats.composited, stats.traversals),
        (1, n as u64, 4)
    );
    // Each hit is taken once, in the batch it belongs to; a leaf test can only take one.
    assert!(
        stats.hits >= n as u64 && stats.leaf_tests >= stats.hits,
        "{stats:?}"
    );
    // A batch resumes after the last hit composited: nodes wholly in front of it are not
    // entered again. Re-entering them, as obvhs's own node test does, tests at least
    // 128 + 256 + 384 + 389 = 1,157 surfels here; without, 609 (a hit taken and later evicted
    // from a full batch is tested again by the next traversal).
    assert!(
        stats.leaf_tests < 2 * n as u64,
        "earlier batches' surfels tested again: {stats:?}"
    );
    let mut vis = RayStats::default();
    let t = placed.transmittance_stats(o, d, 0.0, f32::INFINITY, &mut vis);
    assert_eq!(t, placed.transmittance(o, d, 0.0, f32::INFINITY));
    assert_eq!(
        (vis.rays, vis.hits, vis.traversals, vis.composited),
        (1, n as u64, 1, 0)
    );
    assert!(vis.leaf_tests >= vis.hits);
    // A ray that misses everything enters nothing.
    let mut miss = RayStats::default();
    placed.composite_stats(
        [5.0, 5.0, 1.0],
        [0.0, 0.0, -1.0],
        0.0,
        f32::INFINITY,
        &mut miss,
    );
    assert_eq!((miss.hits, miss.composited, miss.traversals), (0, 0, 0));
}

#[test]
fn an_object_in_front_of_the_background_is_traversed_first() {
    // Component 0 a large background: a faint 3 m wide slab of 400 surfels at z in [-0.5, 0]
    // (0.98^400 ≈ 3e-4 > T_MIN, so on its own all of it is composited); component 1 a
    // small opaque stack in front of it (z = 1). A ray through both is cut at the object:
    // the composite is the object's hits alone, matching the reference, and since the object
    // is traversed first (smallest bounds) the background's traversal is clipped at the cut
    // and takes none of its hits (in component order it took 202 of them first).
    let mut rng = SplitMix(9);
    let mut background = Surfels::with_sh_degree(0);
    for i in 0..400 {
        let mu = [
            rng.range(-0.05, 0.05),
            rng.range(-0.05, 0.05),
            -0.5 * i as f32 / 400.0,
        ];
        push(
            &mut background,
            mu,
            [0.0, 0.0, 0.0, 1.0],
            [1.5, 1.5],
            0.02,
            0.3,
        );
    }
    let mut object = stack(8, 0.9, |i| i as f32 / 8.0);
    for p in object.position.iter_mut() {
        p[2] += 1.0;
    }
    let scene = scene_of(vec![background, object]);
    let id = vec![Rigid::IDENTITY; 2];
    let traced = TraceScene::new(&scene);
    let placed = traced.place(&id);
    let (o, d) = ([0.01, 0.02, 2.0], [0.0, 0.0, -1.0]);
    let mut stats = RayStats::default();
    let fast = placed.composite_stats(o, d, 0.0, f32::INFINITY, &mut stats);
    let slow = composite_brute(&scene, &id, o, d, 0.0, f32::INFINITY);
    assert_eq!(fast.hits, slow.hits);
    close("object in front", &fast, &slow, 1e-5);
    // 0.1^4 = T_MIN: the object's fourth hit ends the ray (α = 0.9 at the centre).
    assert!(fast.hits <= 5, "{fast:?}");
    assert!(stats.hits < 10, "background hits taken: {stats:?}");
    // Without the object, the same ray composites the whole background.
    let alone = scene_of(vec![scene.components[0].surfels.clone()]);
    let traced_alone = TraceScene::new(&alone);
    let r = traced_alone
        .place(&id[..1])
        .composite(o, d, 0.0, f32::INFINITY);
    assert_eq!(r.hits, 400);
}

#[test]
fn equal_depths_break_ties_by_component_then_index() {
    // Identical geometry, so every t is bit-identical in both implementations; only the
    // materials tell the order. Two components share the ties, and 2.5 batches of them.
    let n = 5 * BATCH / 2;
    let mut first = Surfels::with_sh_degree(0);
    let mut second = Surfels::with_sh_degree(0);
    for i in 0..n {
        let c = (i * 37 % 101) as f32 / 101.0;
        let target = if i % 3 == 0 { &mut first } else { &mut second };
        push(
            target,
            [0.0; 3],
            [0.0, 0.0, 0.0, 1.0],
            [0.2, 0.2],
            // Faint enough that all 2.5 batches are composited (Π ≈ 0.015 for BATCH = 128).
            0.01 + 0.00002 * i as f32,
            c,
        );
    }
    let scene = scene_of(vec![second, first]);
    let id = vec![Rigid::IDENTITY; 2];
    let traced = TraceScene::new(&scene);
    let placed = traced.place(&id);
    for (o, d) in [
        ([0.0, 0.0, 2.0], [0.0, 0.0, -1.0]),
        ([0.05, -0.1, -1.0], [0.0, 0.0, 1.0]),
    ] {
        let fast = placed.composite(o, d, 0.0, f32::INFINITY);
        let slow = composite_brute(&scene, &id, o, d, 0.0, f32::INFINITY);
        assert!(fast.hits as usize > BATCH, "{fast:?}");
        assert_eq!(fast.hits, slow.hits);
        close("ties", &fast, &slow, 1e-5);
    }
}

#[test]
fn single_surfel_matches_the_formula() {
    let (su, sv) = (0.1f32, 0.2f32);
    let one = |alpha: f32| {
        let mut s = Surfels::with_sh_degree(0);
        push(
            &mut s,
            [0.0; 3],
            [0.0, 0.0, 0.0, 1.0],
            [su, sv],
            alpha,
            0.25,
        );
        scene_of(vec![s])
    };
    for alpha in [0.5f32, 0.995] {
        let scene = one(alpha);
        let traced = TraceScene::new(&scene);
        let placed = traced.place(&[Rigid::IDENTITY]);
        // Centre: α_eff = min(α, 0.99), at t = 5, normal facing the ray.
        let r = placed.composite([0.0, 0.0, 5.0], [0.0, 0.0, -1.0], 0.0, f32::INFINITY);
        let a = alpha.min(MAX_OPACITY);
        assert_eq!(r.hits, 1);
        assert!((r.alpha - a).abs() < 1e-6, "{r:?}");
        assert!((r.mean_depth() - 5.0).abs() < 1e-5);
        assert_eq!(r.unit_normal(), [0.0, 0.0, 1.0]);
        assert!((r.mean_base_color()[0] - 0.25).abs() < 1e-6);
        assert!(
            (placed.transmittance([0.0, 0.0, 5.0], [0.0, 0.0, -1.0], 0.0, 10.0) - (1.0 - a)).abs()
                < 1e-6
        );
        // From below the normal is flipped to face the ray.
        let r = placed.composite([0.0, 0.0, -2.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY);
        assert_eq!(r.unit_normal(), [0.0, 0.0, -1.0]);
        // |ξ| = 2.5 along v: α·exp(−3.125).
        let r = placed.composite([0.0, 2.5 * sv, 5.0], [0.0, 0.0, -1.0], 0.0, f32::INFINITY);
        let expect = alpha * (-0.5f32 * 2.5 * 2.5).exp();
        assert!(
            (r.alpha - expect).abs() < 1e-5 * expect.max(1.0),
            "{r:?} vs {expect}"
        );
        // Oblique ray through ξ = (1, 1): hit where the plane is crossed.
        let target = glam::Vec3::new(su, sv, 0.0);
        let o = glam::Vec3::new(1.0, -0.5, 2.0);
        let d = (target - o).normalize();
        let r = placed.composite(o.to_array(), d.to_array(), 0.0, f32::INFINITY);
        let expect = (alpha * (-1.0f32).exp()).min(MAX_OPACITY);
        assert!((r.alpha - expect).abs() < 1e-5, "{r:?} vs {expect}");
        let x = r.mean_position();
        assert!(
            (glam::Vec3::from_array(x) - target).length() < 1e-5,
            "{x:?}"
        );
        // Just outside the support: |ξ| = 3.01 gives no hit, 2.99 does.
        let miss = placed.composite([3.01 * su, 0.0, 5.0], [0.0, 0.0, -1.0], 0.0, f32::INFINITY);
        assert_eq!(miss, SurfaceRecord::default());
        let inside = placed.composite([2.99 * su, 0.0, 5.0], [0.0, 0.0, -1.0], 0.0, f32::INFINITY);
        assert_eq!(inside.hits, 1);
        assert_eq!(
            placed.transmittance([3.01 * su, 0.0, 5.0], [0.0, 0.0, -1.0], 0.0, 10.0),
            1.0
        );
    }
    // A faint surfel is invisible where α·G < 1/255 even inside the support.
    let scene = one(0.05);
    let traced = TraceScene::new(&scene);
    let placed = traced.place(&[Rigid::IDENTITY]);
    // 0.05·exp(−½·2.5²) = 2.2e-3 < 1/255.
    let r = placed.composite([0.0, 2.5 * sv, 5.0], [0.0, 0.0, -1.0], 0.0, f32::INFINITY);
    assert_eq!(r.hits, 0);
}

#[test]
fn transmittance_stops_once_negligible() {
    // 0.2^5 = 3.2e-4 ≥ T_MIN > 0.2^6: the sixth surfel ends the ray.
    let scene = scene_of(vec![stack(12, 0.8, |i| i as f32 / 12.0)]);
    let id = vec![Rigid::IDENTITY];
    let traced = TraceScene::new(&scene);
    let placed = traced.place(&id);
    let (o, d) = ([0.0, 0.0, 1.0], [0.0, 0.0, -1.0]);
    assert_eq!(placed.transmittance(o, d, 0.0, f32::INFINITY), 0.0);
    let r = placed.composite(o, d, 0.0, f32::INFINITY);
    assert_eq!(r.hits, 6);
    assert!((r.alpha - (1.0 - 0.2f32.powi(6))).abs() < 1e-6);
    close(
        "early exit",
        &r,
        &composite_brute(&scene, &id, o, d, 0.0, f32::INFINITY),
        1e-5,
    );
    // Ending the segment between the fifth and sixth surfel (t = 1.04, 1.05) keeps it above.
    let t = placed.transmittance(o, d, 0.0, 1.045);
    assert!((t - 0.2f32.powi(5)).abs() < 1e-7, "{t}");
    // Starting it past the first three leaves 0.2^9 < T_MIN.
    assert_eq!(placed.transmittance(o, d, 1.025, f32::INFINITY), 0.0);
    let r = placed.composite(o, d, 1.025, f32::INFINITY);
    assert_eq!(r.hits, 6);
}

#[test]
fn degenerate_rays_give_finite_records() {
    let (scene, transforms) = random_scene(5, (0.2, 1.0), 400);
    let mut flat = Surfels::with_sh_degree(0);
    push(
        &mut flat,
        [0.0; 3],
        [0.0, 0.0, 0.0, 1.0],
        [0.1, 0.1],
        0.9,
        0.5,
    );
    let mut scene = scene;
    scene.components.push(Component {
        name: "flat".into(),
        id: 9,
        surfels: flat,
    });
    let mut transforms = transforms;
    transforms.push(Rigid::IDENTITY);
    let traced = TraceScene::new(&scene);
    let placed = traced.place(&transforms);
    let finite = |r: &SurfaceRecord| {
        [r.depth, r.alpha, r.metallic, r.roughness]
            .iter()
            .chain(&r.position)
            .chain(&r.normal)
            .chain(&r.base_color)
            .all(|x| x.is_finite())
    };
    let mut rays = vec![
        // In the flat surfel's plane, through its centre, and just above it.
        ([-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
        ([-1.0, 0.0, 1e-3], [1.0, 0.0, 0.0]),
        ([-1.0, 0.0, 0.0], [1.0, 0.0, 1e-9]),
        // A zero direction.
        ([0.0, 0.0, 1.0], [0.0, 0.0, 0.0]),
    ];
    // Axis-aligned rays through surfel centres (zero direction components everywhere).
    for c in &scene.components[..2] {
        for p in c.surfels.position.iter().take(20) {
            for d in [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]] {
                rays.push(([p[0] - 3.0 * d[0], p[1] - 3.0 * d[1], p[2] - 3.0 * d[2]], d));
            }
        }
    }
    for (o, d) in rays {
        let r = placed.composite(o, d, 0.0, f32::INFINITY);
        assert!(finite(&r), "{o:?} {d:?}: {r:?}");
        assert!(r.unit_normal().iter().all(|x| x.is_finite()));
        let t = placed.transmittance(o, d, 0.0, f32::INFINITY);
        assert!((0.0..=1.0).contains(&t), "{t}");
    }
    // The in-plane ray misses the edge-on disc in both implementations.
    let (o, d) = ([-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    let only_flat = scene_of(vec![scene.components.last().unwrap().surfels.clone()]);
    let r = composite_brute(&only_flat, &[Rigid::IDENTITY], o, d, 0.0, f32::INFINITY);
    assert_eq!(r.hits, 0);
}

#[test]
fn placing_equals_baking_the_transforms_into_the_surfels() {
    // The same state traced two ways: objects placed by the top level, and objects whose
    // surfels were moved into the world (identity transforms) before their BVH was built.
    let (scene, transforms) = random_scene(6, (0.2, 1.0), 500);
    let mut baked = scene.clone();
    for (c, tf) in baked.components.iter_mut().zip(&transforms) {
        let s = &mut c.surfels;
        for i in 0..s.len() {
            s.position[i] = tf.transform_point(s.position[i]);
            s.rotation[i] = tf.transform_rotation(s.rotation[i]);
        }
    }
    let ids = vec![Rigid::IDENTITY; transforms.len()];
    let traced = TraceScene::new(&scene);
    let traced_baked = TraceScene::new(&baked);
    let placed = traced.place(&transforms);
    let placed_baked = traced_baked.place(&ids);
    // And a second layout from the same TraceScene still agrees with its reference.
    let mut rng = SplitMix(99);
    let other: Vec<Rigid> = (0..transforms.len())
        .map(|i| {
            if i == 0 {
                Rigid::IDENTITY
            } else {
                random_rigid(&mut rng)
            }
        })
        .collect();
    let placed_other = traced.place(&other);
    for _ in 0..80 {
        let (o, d) = random_ray(&mut rng);
        let a = placed.composite(o, d, 0.0, f32::INFINITY);
        let b = placed_baked.composite(o, d, 0.0, f32::INFINITY);
        close("baked", &a, &b, 1e-3);
        let c = placed_other.composite(o, d, 0.0, f32::INFINITY);
        close(
            "other layout",
            &c,
            &composite_brute(&scene, &other, o, d, 0.0, f32::INFINITY),
            1e-3,
        );
    }
}

/// The traversals compiled for AVX2 (`trace::Isa`, chosen at run time) give the baseline build's
/// results bit for bit: composites (record and hits), visibility rays and the composite's
/// backward pass, on opaque-ish and faint random scenes (several batches per ray) with moved
/// objects. This runs the one `unsafe` call of the dispatch; on a CPU without AVX2 both
/// placements are the baseline and the test says so.
#[test]
fn the_avx2_traversals_match_the_baseline_bit_for_bit() {
    use lightfuse::trace::{Isa, RecordGrad, TraceRay};
    if Isa::best() == Isa::Baseline {
        eprintln!("this CPU lacks AVX2: only the baseline traversals ran");
    }
    for (seed, alpha, n) in [(11u64, (0.3, 1.0), 800), (12, (0.004, 0.04), 2400)] {
        let (scene, transforms) = random_scene(seed, alpha, n);
        let traced = TraceScene::new(&scene);
        let best = traced.place(&transforms);
        assert_eq!(best.isa(), Isa::best());
        let base = traced.place(&transforms).with_isa(Isa::Baseline);
        let mut rng = SplitMix(seed + 300);
        let (mut rays, mut grads) = (Vec::new(), Vec::new());
        for r in 0..200 {
            let (o, d) = random_ray(&mut rng);
            let (mut ha, mut hb) = (Vec::new(), Vec::new());
            let a = best.composite_hits(o, d, 0.0, f32::INFINITY, &mut ha);
            let b = base.composite_hits(o, d, 0.0, f32::INFINITY, &mut hb);
            assert_eq!(format!("{a:?} {ha:?}"), format!("{b:?} {hb:?}"), "ray {r}");
            let (ta, tb) = (
                best.transmittance(o, d, 0.0, f32::INFINITY),
                base.transmittance(o, d, 0.0, f32::INFINITY),
            );
            assert_eq!(ta.to_bits(), tb.to_bits(), "ray {r}: {ta} vs {tb}");
            rays.push(TraceRay {
                origin: o,
                dir: d,
                t_min: 0.0,
                t_max: f32::INFINITY,
            });
            let mut u = || rng.range(-0.5, 0.5);
            grads.push(RecordGrad {
                depth: u(),
                position: [u(), u(), u()],
                normal: [u(), u(), u()],
                base_color: [u(), u(), u()],
                metallic: u(),
                roughness: u(),
                alpha: u(),
            });
        }
        let parts: Vec<&Surfels> = scene.components.iter().map(|c| &c.surfels).collect();
        let ga = best.composite_backward(&parts, &rays, &grads, true);
        let gb = base.composite_backward(&parts, &rays, &grads, true);
        assert_eq!(format!("{ga:?}"), format!("{gb:?}"));
    }
}

/// What two scenes that hold the same surfels in different trees composite must not depend on
/// the tree: the same hits (component, surfel) in the same order, with weights and record sums
/// equal up to rounding. Tolerance: the batch's running transmittance is a product of up to a
/// few hundred f32 factors taken in discovery order, each rounding by ≤ 2⁻²⁴ relative, so a
/// weight may move by ~1e-5 of itself (absolute 1e-6 below w = 0.1, where relative error means
/// little); the record's sums add up to a few hundred such weights, so 1e-4 of the sum
/// (absolute below 1); transmittance 1e-5. Returns the number of hits seen.
fn same_composites(
    pm: &lightfuse::trace::Placed,
    pf: &lightfuse::trace::Placed,
    rng: &mut SplitMix,
    rays: usize,
) -> usize {
    let mut total_hits = 0;
    for r in 0..rays {
        let (o, d) = random_ray(rng);
        let (mut hm, mut hf) = (Vec::new(), Vec::new());
        let a = pm.composite_hits(o, d, 0.0, f32::INFINITY, &mut hm);
        let b = pf.composite_hits(o, d, 0.0, f32::INFINITY, &mut hf);
        let ids = |h: &[lightfuse::trace::WeightedHit]| -> Vec<(u32, u32)> {
            h.iter().map(|h| (h.component, h.index)).collect()
        };
        assert_eq!(ids(&hm), ids(&hf), "ray {r}: other hits");
        total_hits += hm.len();
        for (x, y) in hm.iter().zip(&hf) {
            assert!(
                (x.w - y.w).abs() <= 1e-5 * x.w.max(1e-1),
                "ray {r}: {x:?} vs {y:?}"
            );
        }
        assert_eq!(a.hits, b.hits);
        let sums = |s: &lightfuse::trace::SurfaceRecord| {
            let mut v = vec![s.depth, s.metallic, s.roughness, s.alpha];
            v.extend(s.position);
            v.extend(s.normal);
            v.extend(s.base_color);
            v
        };
        for (x, y) in sums(&a).iter().zip(sums(&b)) {
            assert!(
                (x - y).abs() <= 1e-4 * x.abs().max(1.0),
                "ray {r}: {a:?} vs {b:?}"
            );
        }
        let (ta, tb) = (
            pm.transmittance(o, d, 0.0, f32::INFINITY),
            pf.transmittance(o, d, 0.0, f32::INFINITY),
        );
        assert!((ta - tb).abs() <= 1e-5, "ray {r}: {ta} vs {tb}");
    }
    total_hits
}

/// Stage 2's per-step scenes are built with obvhs's very fast build
/// ([`TraceScene::from_components_for_few_rays`]): a different tree, so the same hits are found
/// in another order ([`same_composites`]).
#[test]
fn the_few_rays_build_composites_what_the_medium_build_does() {
    for (seed, alpha, n) in [(21u64, (0.3, 1.0), 1500), (22, (0.004, 0.04), 3000)] {
        let (scene, transforms) = random_scene(seed, alpha, n);
        let parts: Vec<&Surfels> = scene.components.iter().map(|c| &c.surfels).collect();
        let medium = TraceScene::from_components(&parts);
        let fast = TraceScene::from_components_for_few_rays(&parts);
        let (pm, pf) = (medium.place(&transforms), fast.place(&transforms));
        let total_hits = same_composites(&pm, &pf, &mut SplitMix(seed + 500), 300);
        assert!(
            total_hits > 300,
            "the rays must hit something: {total_hits}"
        );
    }
}

/// Stage 2 refits its scene between rebuilds ([`TraceScene::refit`]): built on one set of
/// surfels, then every surfel moved, turned, rescaled, faded or brightened (some to an opacity
/// that can never be hit, whose box is a point) and recoloured, and the old tree refitted.
/// It composites what a tree built on the moved surfels does ([`same_composites`]) and what the
/// f64 reference does ([`close`]), for faint and opaque scenes, and a second refit (as in
/// consecutive steps) too.
#[test]
fn a_refitted_scene_composites_what_a_rebuilt_one_does() {
    for (seed, alpha, n) in [(31u64, (0.3, 1.0), 1500), (32, (0.004, 0.04), 3000)] {
        let (mut scene, transforms) = random_scene(seed, alpha, n);
        let parts: Vec<&Surfels> = scene.components.iter().map(|c| &c.surfels).collect();
        let mut refitted = TraceScene::from_components_for_few_rays(&parts);
        let mut rng = SplitMix(seed + 1);
        for round in 0..2 {
            for c in &mut scene.components {
                let s = &mut c.surfels;
                for i in 0..s.len() {
                    for k in 0..3 {
                        s.position[i][k] += rng.range(-0.15, 0.15);
                    }
                    if rng.f32() < 0.5 {
                        s.rotation[i] = rng.unit_quat();
                    }
                    for k in 0..2 {
                        s.scale[i][k] *= rng.range(0.5, 1.6);
                    }
                    s.opacity[i] = match i % 11 {
                        0 => 1e-4, // never reaches MIN_ALPHA: a point box
                        _ => (s.opacity[i] * rng.range(0.5, 1.5)).min(1.0),
                    };
                    s.base_color[i] = [rng.f32(), rng.f32(), rng.f32()];
                    s.metallic[i] = rng.f32();
                    s.roughness[i] = rng.f32();
                }
            }
            let parts: Vec<&Surfels> = scene.components.iter().map(|c| &c.surfels).collect();
            refitted.refit(&parts);
            let rebuilt = TraceScene::from_components(&parts);
            let (pr, pb) = (refitted.place(&transforms), rebuilt.place(&transforms));
            let hits = same_composites(&pb, &pr, &mut SplitMix(seed + 10 + round), 300);
            assert!(hits > 300, "the rays must hit something: {hits}");
            let mut rng_ray = SplitMix(seed + 20 + round);
            for r in 0..60 {
                let (o, d) = random_ray(&mut rng_ray);
                let fast = pr.composite(o, d, 0.0, f32::INFINITY);
                let slow = composite_brute(&scene, &transforms, o, d, 0.0, f32::INFINITY);
                close(&format!("round {round} ray {r}"), &fast, &slow, 1e-3);
            }
        }
    }
}
