//! Tracing speed on a scene that looks like a surfelized room: floor, ceiling and three walls
//! sampled on a jittered lattice (σ = spacing, as `surfelize` does), plus three spheres that are
//! separate components placed by rigid transforms (so the two-level path is what is measured).
//!
//! - `trace_build`: BVHs for 200k and 1M surfels (all components).
//! - `trace_rays_200k`: composited camera rays (640×480 pinhole view into the room) and
//!   visibility rays (from random surface points in random hemisphere directions), all rays in
//!   parallel with rayon; criterion reports rays/s.
//!
//! - `trace_backward_200k`: a batch of 16,384 camera rays (a 128×128 view into the room):
//!   the composited forward pass, then `composite_backward` for upstream gradients of the mean
//!   depth, the unit normal and the opacity (with placement gradients); rays/s of the pair.
//!
//! - `render_128x128_32spp`: a whole image of the one-bounce estimator (eq. path-estimator) into
//!   the room, lit by a smooth synthetic sky through its open side: 128×128 pixels at 32 spp,
//!   rayon over rows, as `lightfuse render` does for a view (the Cycles comparison of the same
//!   work is `lightfuse bench`).
//!
//! - `render_reconstruction_16spp`: the same one-bounce image at 16 spp of a *learned* scene,
//!   stage 1's reconstruction of the demo dataset (`bash scripts/bench_scene.sh` makes it in
//!   `data/bench`; `LIGHTFUSE_BENCH_DIR` points elsewhere; skipped with a message when absent),
//!   from the dataset's first camera of its first state, in that state's placement; throughput is
//!   path samples. Learned surfels are larger, overlap more and are less opaque than surfelized
//!   meshes, so this is what stages 2-3 and `evaluate` pay. Also printed for both scenes: leaf
//!   tests, hits taken and hits composited per camera ray, and leaf tests and hits per
//!   visibility ray (from each camera ray's surface, 1 mm off it, into a random direction of its
//!   hemisphere).
//!
//! Run: `cargo bench --bench trace`. Numbers are noisy on a shared machine.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use glam::{Mat3, Quat, Vec3};
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::{Camera, Component, Environment, Rigid, Scene, Surfels};
use lightfuse::shade::envmap::EnvMap;
use lightfuse::shade::estimator::{self_hit_epsilon, Estimator, PixelFilter};
use lightfuse::shade::Sampler;
use lightfuse::trace::{RecordGrad, TraceRay, TraceScene};
use rayon::prelude::*;
use std::hint::black_box;
use std::time::Duration;

/// Room half-width and height, metres.
const HALF: f32 = 4.0;
const HEIGHT: f32 = 3.0;
/// Spheres: centre (placed by the component's transform) and radius.
const SPHERES: [([f32; 3], f32); 3] = [
    ([-1.2, 0.7, -1.0], 0.7),
    ([1.0, 0.5, 0.2], 0.5),
    ([0.2, 0.9, -2.4], 0.9),
];

fn push(s: &mut Surfels, rng: &mut SplitMix, mu: Vec3, frame: Mat3, h: f32) {
    let color = [rng.f32(), rng.f32(), rng.f32()];
    s.push(
        mu.to_array(),
        Quat::from_mat3(&frame).normalize().to_array(),
        [h, h],
        rng.range(0.9, 1.0),
        &[[0.0; 3]],
        color,
        rng.f32(),
        rng.range(0.1, 1.0),
    );
}

/// A jittered lattice of pitch h on the rectangle corner + a·e1 + b·e2, a ∈ [0, la], b ∈ [0, lb],
/// normal e1 × e2.
#[allow(clippy::too_many_arguments)]
fn plane(
    s: &mut Surfels,
    rng: &mut SplitMix,
    corner: Vec3,
    e1: Vec3,
    e2: Vec3,
    la: f32,
    lb: f32,
    h: f32,
) {
    let frame = Mat3::from_cols(e1, e2, e1.cross(e2));
    let (na, nb) = ((la / h) as usize, (lb / h) as usize);
    for i in 0..na {
        for j in 0..nb {
            let a = (i as f32 + 0.5 + rng.range(-0.25, 0.25)) * h;
            let b = (j as f32 + 0.5 + rng.range(-0.25, 0.25)) * h;
            push(s, rng, corner + a * e1 + b * e2, frame, h);
        }
    }
}

/// Fibonacci points on a sphere of radius r at the origin, about r²·4π / h² of them, normals out.
fn sphere(s: &mut Surfels, rng: &mut SplitMix, r: f32, h: f32) {
    let n = (4.0 * std::f32::consts::PI * r * r / (h * h)) as usize;
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    for i in 0..n {
        let y = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
        let ring = (1.0 - y * y).sqrt();
        let phi = golden * i as f32;
        let normal = Vec3::new(ring * phi.cos(), y, ring * phi.sin());
        let tangent = normal.any_orthonormal_vector();
        let frame = Mat3::from_cols(tangent, normal.cross(tangent), normal);
        push(s, rng, r * normal, frame, h);
    }
}

/// About `n` surfels: the room is the background, each sphere an object placed by its state
/// transform (translation plus a turn, so the object frame is not the world frame).
fn room(n: usize) -> Scene {
    let walls = 2.0 * (2.0 * HALF) * (2.0 * HALF) + 3.0 * (2.0 * HALF) * HEIGHT;
    let balls: f32 = SPHERES
        .iter()
        .map(|(_, r)| 4.0 * std::f32::consts::PI * r * r)
        .sum();
    let h = ((walls + balls) / n as f32).sqrt();
    let mut rng = SplitMix(7);
    let mut bg = Surfels::with_sh_degree(0);
    let (x, y, z) = (Vec3::X, Vec3::Y, Vec3::Z);
    let w = 2.0 * HALF;
    // Normals point into the room.
    plane(
        &mut bg,
        &mut rng,
        Vec3::new(-HALF, 0.0, HALF),
        x,
        -z,
        w,
        w,
        h,
    ); // floor, +y
    plane(
        &mut bg,
        &mut rng,
        Vec3::new(-HALF, HEIGHT, -HALF),
        x,
        z,
        w,
        w,
        h,
    ); // ceiling, −y
    plane(
        &mut bg,
        &mut rng,
        Vec3::new(-HALF, 0.0, -HALF),
        x,
        y,
        w,
        HEIGHT,
        h,
    ); // back, +z
    plane(
        &mut bg,
        &mut rng,
        Vec3::new(-HALF, 0.0, HALF),
        -z,
        y,
        w,
        HEIGHT,
        h,
    ); // left, +x
    plane(
        &mut bg,
        &mut rng,
        Vec3::new(HALF, 0.0, -HALF),
        z,
        y,
        w,
        HEIGHT,
        h,
    ); // right, −x
    let mut scene = Scene::from_background(bg);
    for (k, (centre, r)) in SPHERES.iter().enumerate() {
        let mut s = Surfels::with_sh_degree(0);
        sphere(&mut s, &mut rng, *r, h);
        scene.components.push(Component {
            name: format!("sphere{k}"),
            id: k as u32 + 1,
            surfels: s,
        });
        scene.states[0].transforms.push(Rigid {
            rotation: Quat::from_rotation_y(0.3 + k as f32).to_array(),
            translation: *centre,
        });
    }
    scene
}

/// A 640×480 camera near the front wall looking into the room (docs/design.md §2).
fn camera() -> Camera {
    camera_of(640, 480)
}

fn camera_of(w: u32, h: u32) -> Camera {
    let fl = 0.5 * w as f32 / (0.5 * 70f32.to_radians()).tan();
    Camera::look_at([0.3, 1.6, 3.6], [0.0, 0.8, -2.0], w, h, fl)
}

/// A ray leaving the surface point `p` of normal `n`, 1 mm off it, into a random direction of
/// the hemisphere `n` faces.
fn leave_surface(rng: &mut SplitMix, p: Vec3, n: Vec3) -> ([f32; 3], [f32; 3]) {
    let mut d = Vec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    )
    .normalize();
    if d.dot(n) < 0.0 {
        d = -d;
    }
    ((p + 1e-3 * n).to_array(), d.to_array())
}

/// Visibility rays leaving random surfels (1 mm off the surface) into random directions of the
/// hemisphere their normal faces.
fn visibility_rays(scene: &Scene, count: usize) -> Vec<([f32; 3], [f32; 3])> {
    let mut rng = SplitMix(11);
    let state = &scene.states[0];
    let total = scene.surfel_count();
    (0..count)
        .map(|_| {
            let mut i = (rng.next_u64() % total as u64) as usize;
            let mut c = 0;
            while i >= scene.components[c].surfels.len() {
                i -= scene.components[c].surfels.len();
                c += 1;
            }
            let s = &scene.components[c].surfels;
            let tf = state.transforms[c];
            let p = Vec3::from_array(tf.transform_point(s.position[i]));
            let n = Quat::from_array(tf.transform_rotation(s.rotation[i])) * Vec3::Z;
            leave_surface(&mut rng, p, n)
        })
        .collect()
}

fn build(c: &mut Criterion) {
    let mut group = c.benchmark_group("trace_build");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(15));
    for n in [200_000usize, 1_000_000] {
        let scene = room(n);
        group.throughput(Throughput::Elements(scene.surfel_count() as u64));
        group.bench_with_input(BenchmarkId::from_parameter(n), &scene, |b, scene| {
            b.iter(|| TraceScene::new(scene))
        });
    }
    group.finish();
}

fn rays(c: &mut Criterion) {
    let scene = room(200_000);
    let traced = TraceScene::new(&scene);
    let placed = traced.place_state(&scene.states[0]);
    let cam = camera();
    let pixels = (cam.w * cam.h) as usize;
    let vis = visibility_rays(&scene, 200_000);

    let mut group = c.benchmark_group("trace_rays_200k");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(10));
    group.throughput(Throughput::Elements(pixels as u64));
    group.bench_function("composite_camera", |b| {
        b.iter(|| {
            (0..cam.h)
                .into_par_iter()
                .map(|y| {
                    let mut acc = 0.0f32;
                    for x in 0..cam.w {
                        let (o, d) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
                        acc += placed.composite(o, d, 0.0, f32::INFINITY).alpha;
                    }
                    acc
                })
                .sum::<f32>()
        })
    });
    group.throughput(Throughput::Elements(vis.len() as u64));
    group.bench_function("visibility", |b| {
        b.iter(|| {
            vis.par_chunks(256)
                .map(|chunk| {
                    chunk
                        .iter()
                        .map(|(o, d)| placed.transmittance(*o, *d, 0.0, f32::INFINITY))
                        .sum::<f32>()
                })
                .sum::<f32>()
        })
    });
    group.finish();

    // What the rays saw, so a reader can tell the scene is a closed, opaque room.
    let (mut hits, mut alpha) = (0u64, 0.0f64);

    for y in (0..cam.h).step_by(8) {
        for x in (0..cam.w).step_by(8) {
            let (o, d) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
            let r = placed.composite(o, d, 0.0, f32::INFINITY);
            hits += r.hits as u64;
            alpha += r.alpha as f64;
        }
    }
    let m = ((cam.w / 8) * (cam.h / 8)) as f64;

    let open = vis
        .iter()
        .map(|(o, d)| placed.transmittance(*o, *d, 0.0, f32::INFINITY))
        .filter(|t| *t > 0.0)
        .count();
    black_box(&traced);
    eprintln!(
        "scene: {} surfels; camera rays: mean alpha {:.5}, mean hits composited {:.1}; \
         visibility rays not fully blocked: {open} of {}",
        scene.surfel_count(),
        alpha / m,
        hits as f64 / m,
        vis.len()
    );
}

/// A smooth sky: brighter towards +Y and towards one side, 128×64 texels.
fn backward(c: &mut Criterion) {
    let scene = room(200_000);
    let traced = TraceScene::new(&scene);
    let placed = traced.place_state(&scene.states[0]);
    let parts: Vec<&Surfels> = scene.components.iter().map(|c| &c.surfels).collect();
    let cam = camera_of(128, 128);
    let rays: Vec<TraceRay> = (0..cam.h)
        .flat_map(|y| (0..cam.w).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (origin, dir) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
            TraceRay {
                origin,
                dir,
                t_min: 0.0,
                t_max: f32::INFINITY,
            }
        })
        .collect();

    let mut group = c.benchmark_group("trace_backward_200k");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(10));
    group.throughput(Throughput::Elements(rays.len() as u64));
    group.bench_function("depth_normal_alpha", |b| {
        b.iter(|| {
            // Forward, then an L1-like upstream gradient of depth, normal and opacity.
            let grads: Vec<RecordGrad> = rays
                .par_iter()
                .map(|r| {
                    let rec = placed.composite(r.origin, r.dir, r.t_min, r.t_max);
                    let mut g = rec.mean_depth_grad(1.0);
                    g.add(&rec.unit_normal_grad([0.3, 0.5, 0.2]));
                    g.alpha += 1.0;
                    g
                })
                .collect();
            placed.composite_backward(&parts, &rays, &grads, true)
        })
    });
    group.finish();
}

fn sky() -> Environment {
    let (w, h) = (128usize, 64usize);
    let px = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f32 / w as f32, (i / w) as f32 / h as f32);
            let up = (1.0 - y).powi(2);
            [0.3 + 1.5 * up + x, 0.35 + 1.6 * up, 0.4 + 2.0 * up]
        })
        .collect();
    Environment::new("sky", w, h, px)
}

fn render(c: &mut Criterion) {
    let scene = room(200_000);
    let traced = TraceScene::new(&scene);
    let placed = traced.place_state(&scene.states[0]);
    let env = EnvMap::new(&sky(), 0.0);
    let estimator = Estimator::new(&placed, &env, self_hit_epsilon(&scene, &scene.states[0]));
    let filter = PixelFilter::new(1.5);
    let cam = camera_of(128, 128);
    let mut group = c.benchmark_group("render_128x128_32spp");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(20));
    group.throughput(Throughput::Elements((cam.w * cam.h) as u64));
    group.bench_function("one_bounce", |b| {
        b.iter(|| {
            (0..cam.h)
                .into_par_iter()
                .map(|y| {
                    (0..cam.w)
                        .map(|x| estimator.pixel(&cam, &filter, (x, y), 32, 0).rgb[1])
                        .sum::<f32>()
                })
                .sum::<f32>()
        })
    });
    group.finish();
}

/// Stage 3's two passes on the 200k room, 16,384 path samples (64x64 pixels, 4 spp), as
/// `Inverter::step` runs them: the forward estimate and the path replay adjoint (each sample
/// walked again, its adjoint into the texels and the records' materials, and those into every
/// hit surfel's material). `traced` traces every camera ray and runs the full composite
/// backward; `cached` is stage 3's own code (`Passes`): it starts from primary records traced
/// once (`PrimaryCache`: geometry is fixed) and scatters material gradients through the kept
/// hit weights and the hits the replayed continuation composited. The adjoint/forward ratio of
/// each is what issue 12 asks about (aim ≤ 1.5).
fn path_replay(c: &mut Criterion) {
    use lightfuse::io::dataset::Observation;
    use lightfuse::stages::invert::cache::PrimaryCache;
    use lightfuse::stages::invert::cache::TrainState;
    use lightfuse::stages::invert::train::Passes;
    let scene = room(200_000);
    let traced = TraceScene::new(&scene);
    let placed = traced.place_state(&scene.states[0]);
    let parts: Vec<&Surfels> = scene.components.iter().map(|c| &c.surfels).collect();
    let env = EnvMap::new(&sky(), 0.0);
    let eps = self_hit_epsilon(&scene, &scene.states[0]);
    let estimator = Estimator::new(&placed, &env, eps);
    let cam = camera_of(64, 64);
    let filter = PixelFilter::new(lightfuse::shade::estimator::DEFAULT_FILTER_WIDTH);
    const SPP: u32 = 4;
    let samples: Vec<(u32, u32)> = (0..cam.w * cam.h)
        .flat_map(|p| (0..SPP).map(move |i| (p, i)))
        .collect();
    let ray = |p: u32, i: u32, s: &Sampler| filter.camera_ray(&cam, (p % cam.w, p / cam.w), s, i);
    let n = (cam.w * cam.h) as usize;
    let view = Observation {
        state: 0,
        view: 0,
        camera: cam,
        rgb: vec![[0.0; 3]; n],
        depth: vec![0.0; n],
        normal: vec![[0.0; 3]; n],
        mask: vec![0; n],
    };
    let states = [TrainState {
        views: vec![&view],
        transforms: scene.states[0].transforms.clone(),
        eps,
    }];
    // One sub-pixel position per pixel, as stage 3 runs by default (`Settings::primary_jitters`):
    // every sample of a pixel starts at its one record.
    let cache = PrimaryCache::build(&traced, &states, 1, 0);
    let f = cache.figures();
    eprintln!(
        "path_replay_200k: primary cache of {} entries, {:.1} hits each, {:.1} MB, traced in {:.2} s",
        f.entries,
        f.hits as f64 / f.entries as f64,
        f.bytes as f64 / 1e6,
        f.seconds
    );
    let mut group = c.benchmark_group("path_replay_200k");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(15));
    group.throughput(Throughput::Elements(samples.len() as u64));
    group.bench_function("forward_traced", |b| {
        b.iter(|| {
            samples
                .par_iter()
                .map(|&(p, i)| {
                    let s = Sampler::new(p, 0);
                    let (o, d) = ray(p, i, &s);
                    estimator.radiance(o, d, &s, i).radiance[1]
                })
                .sum::<f32>()
        })
    });
    group.bench_function("adjoint_traced", |b| {
        b.iter(|| {
            let per: Vec<(Vec<TraceRay>, Vec<RecordGrad>, f32)> = samples
                .par_chunks(64)
                .map(|chunk| {
                    let (mut rays, mut grads, mut texels) = (Vec::new(), Vec::new(), 0.0f32);
                    for &(p, i) in chunk {
                        let s = Sampler::new(p, 0);
                        let (o, d) = ray(p, i, &s);
                        let path = estimator.replay(o, d, &s, i);
                        let mg = path.adjoint(&env, [1e-3, 1e-3, 1e-3], |_, g| texels += g[1]);
                        for (r, g) in path.record_grads(&mg).into_iter().flatten() {
                            rays.push(r);
                            grads.push(g);
                        }
                    }
                    (rays, grads, texels)
                })
                .collect();
            let (mut rays, mut grads) = (Vec::new(), Vec::new());
            for (r, g, _) in per {
                rays.extend(r);
                grads.extend(g);
            }
            placed.composite_backward(&parts, &rays, &grads, false)
        })
    });
    let passes = Passes {
        estimator: &estimator,
        env: &env,
        cache: &cache,
        image: 0,
        components: &parts,
        spp: SPP,
    };
    let pixels: Vec<u32> = (0..cam.w * cam.h).collect();
    let ybar = vec![[1e-3f32; 3]; pixels.len()];
    group.bench_function("forward_cached", |b| b.iter(|| passes.forward(&pixels, 0)));
    group.bench_function("adjoint_cached", |b| {
        b.iter(|| passes.adjoint(&pixels, &ybar, 0, true))
    });
    group.finish();
}

/// Leaf tests and hits per camera ray (pixel centres) and per visibility ray leaving each
/// camera ray's surface into its hemisphere, printed for the record.
fn print_ray_stats(name: &str, placed: &lightfuse::trace::Placed, cam: &Camera) {
    use lightfuse::trace::RayStats;
    let (mut primary, mut vis) = (RayStats::default(), RayStats::default());
    let mut rng = SplitMix(5);
    for y in 0..cam.h {
        for x in 0..cam.w {
            let (o, d) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
            let rec = placed.composite_stats(o, d, 0.0, f32::INFINITY, &mut primary);
            if rec.hits == 0 || rec.alpha < 0.5 {
                continue;
            }
            let n = Vec3::from_array(rec.unit_normal());
            let p = Vec3::from_array(rec.position) / rec.alpha;
            let (o, dir) = leave_surface(&mut rng, p, n);
            placed.transmittance_stats(o, dir, 0.0, f32::INFINITY, &mut vis);
        }
    }
    let per = |v: u64, s: &RayStats| v as f64 / s.rays.max(1) as f64;
    eprintln!(
        "{name}: per camera ray {:.1} nodes, {:.1} leaf tests, {:.1} hits taken, {:.1} composited, {:.2} traversals; \
         per visibility ray {:.1} nodes, {:.1} leaf tests, {:.1} hits ({} rays)",
        per(primary.nodes, &primary),
        per(primary.leaf_tests, &primary),
        per(primary.hits, &primary),
        per(primary.composited, &primary),
        per(primary.traversals, &primary),
        per(vis.nodes, &vis),
        per(vis.leaf_tests, &vis),
        per(vis.hits, &vis),
        vis.rays
    );
}

/// Stage 1's reconstruction of the demo (see the module doc), if `scripts/bench_scene.sh` made it.
fn reconstruction(c: &mut Criterion) {
    use lightfuse::io::cameras::read_views;
    let dir = std::env::var("LIGHTFUSE_BENCH_DIR").unwrap_or_else(|_| "data/bench".into());
    let dir = std::path::Path::new(&dir);
    // Benches run in the package root.
    let (scene_path, dataset) = (dir.join("recon/scene.glb"), dir.join("dataset"));
    if !scene_path.is_file() || !dataset.join("dataset.json").is_file() {
        eprintln!(
            "render_reconstruction_16spp: skipped, no {} (make it with `bash scripts/bench_scene.sh`)",
            scene_path.display()
        );
        return;
    }
    let scene = lightfuse::io::gltf::read(&scene_path).expect("reading the bench reconstruction");
    let views = read_views(&dataset, None, &scene.states[0].name).expect("reading its cameras");
    let cam = views[0].camera;
    let traced = TraceScene::new(&scene);
    let placed = traced.place_state(&scene.states[0]);
    let env = EnvMap::new(&sky(), 0.0);
    let estimator = Estimator::new(&placed, &env, self_hit_epsilon(&scene, &scene.states[0]));
    let filter = PixelFilter::new(1.5);
    const SPP: u32 = 16;
    print_ray_stats(
        &format!(
            "reconstruction ({} surfels, {}x{} view {})",
            scene.surfel_count(),
            cam.w,
            cam.h,
            views[0].name
        ),
        &placed,
        &cam,
    );
    let room = room(200_000);
    let room_traced = TraceScene::new(&room);
    print_ray_stats(
        "200k room (640x480)",
        &room_traced.place_state(&room.states[0]),
        &camera(),
    );
    let mut group = c.benchmark_group("render_reconstruction_16spp");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(20));
    group.throughput(Throughput::Elements((cam.w * cam.h * SPP) as u64));
    group.bench_function("one_bounce", |b| {
        b.iter(|| {
            (0..cam.h)
                .into_par_iter()
                .map(|y| {
                    (0..cam.w)
                        .map(|x| estimator.pixel(&cam, &filter, (x, y), SPP, 0).rgb[1])
                        .sum::<f32>()
                })
                .sum::<f32>()
        })
    });
    group.finish();
}

criterion_group!(
    benches,
    build,
    rays,
    backward,
    render,
    path_replay,
    reconstruction
);
criterion_main!(benches);
