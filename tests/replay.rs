//! Path replay (`shade::replay`) and its adjoint, in the style of Mitsuba 3's AD tests: the
//! replayed estimate is exactly linear in the texels and affine in the base colour; the adjoint
//! matches central finite differences of the *replayed* estimate (same seed, decisions frozen)
//! for base colour, metallic, roughness and texels (at a pole and across the seam included); the
//! dot-product identity holds; a path that contributes nothing gets no gradient; a walk started
//! from a kept primary record (stage 3's cache) is the traced walk.
//!
//! The objective is J = Σ_paths ⟨ȳ_p, L_p⟩ with fixed random ȳ_p, over every path sample of a
//! small image of a floor and a sphere whose surfels each have their own material.
//!
//! Tolerances. The replayed estimate is exactly linear in texels, so a central difference is
//! exact up to f32 rounding of sums of ~10³ terms (relative 1e-4 allowed). In the base colour it
//! is affine: central differences are exact too. In metallic the BRDF is affine as well; in
//! roughness it is smooth (α = r², r ≥ 0.2 keeps clear of the α clamp), and the O(ε²) error of a
//! central difference with ε = 1e-3 is ~1e-6 relative; what dominates is f32 rounding of J
//! (~1e-7 · Σ|terms| / (2ε)), allowed as 2e-3 of the gradient plus 2e-4 of J's scale per unit ε.

#![allow(clippy::needless_range_loop)] // channel loops read clearer indexed

use glam::Vec3;
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::Material;
use lightfuse::scene::{Environment, Scene, Surfels};
use lightfuse::shade::brdf::MaterialGrad;
use lightfuse::shade::estimator::{self_hit_epsilon, Estimator, Strategy};
use lightfuse::shade::replay::PathReplay;
use lightfuse::shade::{EnvMap, Sampler};
use lightfuse::trace::{Placed, RecordGrad, SurfaceRecord, TraceGradients, TraceRay, TraceScene};

mod common;
use common::surfel_scenes::{camera, floor, mat, random_env, scene_of, sphere};

/// Each surfel its own material, drawn about the part's.
fn varied(mut s: Surfels, rng: &mut SplitMix) -> Surfels {
    for i in 0..s.len() {
        s.base_color[i] = s.base_color[i].map(|c| (c * (0.7 + 0.6 * rng.f32())).clamp(0.02, 0.98));
        s.metallic[i] = (s.metallic[i] + 0.3 * (rng.f32() - 0.5)).clamp(0.0, 1.0);
        s.roughness[i] = (s.roughness[i] + 0.2 * (rng.f32() - 0.5)).clamp(0.2, 1.0);
    }
    s
}

fn test_scene() -> Scene {
    let mut rng = SplitMix(17);
    scene_of(vec![
        varied(
            floor(-0.5, 1.2, 0.1, mat([0.6, 0.5, 0.4], 0.2, 0.7)),
            &mut rng,
        ),
        varied(
            sphere(Vec3::ZERO, 0.5, 1200, mat([0.8, 0.4, 0.2], 0.6, 0.35)),
            &mut rng,
        ),
    ])
}

/// A small map, so that every texel is read by many paths; rotated, so the seam is not at the
/// image's edge in world space.
const ENV_W: usize = 16;
const ENV_H: usize = 8;
const ROTATION: f32 = 30.0;

struct Fixture {
    scene: Scene,
    env: Environment,
}

impl Fixture {
    fn new() -> Fixture {
        Fixture {
            scene: test_scene(),
            env: random_env(ENV_W, ENV_H, 7, 1.0),
        }
    }
}

/// Every path sample of a 12x12 view (2 spp; [`replays_bounces`]: `spp`), with its upstream
/// gradient ȳ.
fn replays(placed: &Placed, scene: &Scene, map: &EnvMap) -> Vec<(PathReplay, [f32; 3])> {
    replays_with(placed, scene, map, Strategy::Full)
}

fn replays_with(
    placed: &Placed,
    scene: &Scene,
    map: &EnvMap,
    strategy: Strategy,
) -> Vec<(PathReplay, [f32; 3])> {
    replays_bounces(placed, scene, map, strategy, 1, 2)
}

fn replays_bounces(
    placed: &Placed,
    scene: &Scene,
    map: &EnvMap,
    strategy: Strategy,
    bounces: u32,
    spp: u32,
) -> Vec<(PathReplay, [f32; 3])> {
    let est = Estimator::new(placed, map, self_hit_epsilon(scene, &scene.states[0]))
        .with_strategy(strategy)
        .with_bounces(bounces);
    let cam = camera(Vec3::new(0.2, -0.05, 1.7), 12, 12, 7.0);
    let mut rng = SplitMix(3);
    let mut out = Vec::new();
    for y in 0..12 {
        for x in 0..12 {
            let (o, d) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
            let s = Sampler::new(y * 12 + x, 1);
            for i in 0..spp {
                let ybar = [rng.f32() - 0.3, rng.f32() - 0.3, rng.f32() - 0.3];
                out.push((est.replay(o, d, &s, i), ybar));
            }
        }
    }
    out
}

fn material_of(rec: &SurfaceRecord) -> Material {
    Material {
        base_color: rec.mean_base_color(),
        metallic: rec.mean_metallic(),
        roughness: rec.mean_roughness(),
    }
}

fn dot3(a: [f32; 3], b: [f32; 3]) -> f64 {
    (0..3).map(|c| a[c] as f64 * b[c] as f64).sum()
}

/// J with the paths' decisions frozen, materials from `scene` (same geometry as the replayed
/// one: the records' hits and weights are the same) and texels from `env`.
fn objective(paths: &[(PathReplay, [f32; 3])], scene: &Scene, env: &Environment) -> f64 {
    let trace = TraceScene::new(scene);
    let placed = trace.place_state(&scene.states[0]);
    let map = EnvMap::new(env, ROTATION);
    let mut j = 0.0f64;
    for (p, ybar) in paths {
        let r = &p.camera;
        let m1 = material_of(&placed.composite(r.origin, r.dir, r.t_min, r.t_max));
        let m2 = p.continuation.map_or(p.materials[1], |(r, _)| {
            material_of(&placed.composite(r.origin, r.dir, r.t_min, r.t_max))
        });
        j += dot3(*ybar, p.radiance_with(&[m1, m2], &map));
    }
    j
}

/// The adjoint of J: texel gradients and every surfel's gradients.
fn adjoint(
    paths: &[(PathReplay, [f32; 3])],
    placed: &Placed,
    scene: &Scene,
    map: &EnvMap,
) -> (Vec<[f64; 3]>, TraceGradients) {
    let mut texels = vec![[0.0f64; 3]; ENV_W * ENV_H];
    let mut rays: Vec<TraceRay> = Vec::new();
    let mut grads: Vec<RecordGrad> = Vec::new();
    for (p, ybar) in paths {
        let mg = p.adjoint(map, *ybar, |i, g| {
            for c in 0..3 {
                texels[i][c] += g[c] as f64;
            }
        });
        for (ray, g) in p.record_grads(&mg).into_iter().flatten() {
            rays.push(ray);
            grads.push(g);
        }
    }
    let comps: Vec<&Surfels> = scene.components.iter().map(|c| &c.surfels).collect();
    let surf = placed.composite_backward(&comps, &rays, &grads, false);
    (texels, surf)
}

#[test]
fn forward_is_the_sum_of_the_replayed_terms() {
    let f = Fixture::new();
    let trace = TraceScene::new(&f.scene);
    let placed = trace.place_state(&f.scene.states[0]);
    let map = EnvMap::new(&f.env, ROTATION);
    let est = Estimator::new(
        &placed,
        &map,
        self_hit_epsilon(&f.scene, &f.scene.states[0]),
    );
    let paths = replays(&placed, &f.scene, &map);
    let (mut with_bounce, mut with_secondary) = (0, 0);
    for (p, _) in &paths {
        // The BRDF values kept in the replay are the ones its materials give.
        let a = p.radiance(&map);
        let b = p.radiance_with(&p.materials, &map);
        for c in 0..3 {
            assert!(
                (a[c] - b[c]).abs() <= 1e-6 * a[c].abs().max(1e-3),
                "{a:?} vs {b:?}"
            );
        }
        with_bounce += p.terms().iter().any(|t| t.primary.is_some()) as u32;
        with_secondary += p.terms().iter().any(|t| t.secondary.is_some()) as u32;
    }
    assert!(
        with_bounce > 100 && with_secondary >= 10,
        "{with_bounce} {with_secondary}"
    );
    // And `radiance` is the replay's sum, bit for bit.
    let cam = camera(Vec3::new(0.2, -0.05, 1.7), 12, 12, 7.0);
    let (o, d) = cam.ray(6.5, 7.5);
    let s = Sampler::new(90, 1);
    for i in 0..8 {
        let p = est.replay(o, d, &s, i);
        let r = est.radiance(o, d, &s, i);
        assert_eq!(r.radiance, p.radiance(&map));
        assert_eq!(r.rays, p.rays);
        // Stage 3's cached start: the same walk from the camera ray's kept record, bit for
        // bit, minus the camera ray itself.
        let ray = p.camera;
        let kept = placed.composite(ray.origin, ray.dir, ray.t_min, ray.t_max);
        let q = est.replay_from(ray, kept, &s, i);
        assert_eq!(q.terms(), p.terms());
        assert_eq!(q.continuation, p.continuation);
        assert_eq!(q.rays + 1, p.rays);
    }
}

#[test]
fn replayed_estimate_is_linear_in_texels_and_affine_in_base_colour() {
    let f = Fixture::new();
    let trace = TraceScene::new(&f.scene);
    let placed = trace.place_state(&f.scene.states[0]);
    let map = EnvMap::new(&f.env, ROTATION);
    let paths = replays(&placed, &f.scene, &map);
    let e2 = random_env(ENV_W, ENV_H, 8, 2.0);
    let mix = |a: f32, b: f32| {
        let mut e = f.env.clone();
        for (p, q) in e.pixels.iter_mut().zip(&e2.pixels) {
            *p = [0, 1, 2].map(|c| a * p[c] + b * q[c]);
        }
        EnvMap::new(&e, ROTATION)
    };
    let (m1, m2, m12) = (mix(1.0, 0.0), mix(0.0, 1.0), mix(0.7, -1.9));
    let mut rng = SplitMix(5);
    for (p, _) in &paths {
        let a = p.radiance_with(&p.materials, &m1);
        let b = p.radiance_with(&p.materials, &m2);
        let ab = p.radiance_with(&p.materials, &m12);
        for c in 0..3 {
            let want = 0.7 * a[c] - 1.9 * b[c];
            let scale = 0.7 * a[c].abs() + 1.9 * b[c].abs();
            assert!(
                (ab[c] - want).abs() <= 1e-5 * scale + 1e-9,
                "texels: {ab:?} vs {want}"
            );
        }
        // Affine in each record's base colour: an affine combination λ c₁ + (1 − λ) c₂, λ
        // outside [0, 1] too, gives the same combination of radiances.
        let mut mats_a = p.materials;
        let mut mats_b = p.materials;
        for k in 0..2 {
            mats_a[k].base_color = [rng.f32(), rng.f32(), rng.f32()];
            mats_b[k].base_color = [rng.f32(), rng.f32(), rng.f32()];
        }
        let lam = 2.3f32;
        let mut mats_l = p.materials;
        for k in 0..2 {
            mats_l[k].base_color = [0, 1, 2]
                .map(|c| lam * mats_a[k].base_color[c] + (1.0 - lam) * mats_b[k].base_color[c]);
        }
        for k in 0..2 {
            let mut ma = p.materials;
            let mut mb = p.materials;
            let mut ml = p.materials;
            ma[k].base_color = mats_a[k].base_color;
            mb[k].base_color = mats_b[k].base_color;
            ml[k].base_color = mats_l[k].base_color;
            let (la, lb, ll) = (
                p.radiance_with(&ma, &map),
                p.radiance_with(&mb, &map),
                p.radiance_with(&ml, &map),
            );
            for c in 0..3 {
                let want = lam * la[c] + (1.0 - lam) * lb[c];
                let scale = lam * la[c].abs() + (lam - 1.0) * lb[c].abs();
                assert!(
                    (ll[c] - want).abs() <= 2e-5 * scale + 1e-9,
                    "record {k} base colour: {ll:?} vs {want}"
                );
            }
        }
    }
}

/// Relative agreement of an adjoint and a finite difference, with an absolute floor.
fn agree(adj: f64, fd: f64, floor: f64, what: &str) {
    let err = (adj - fd).abs();
    assert!(
        err <= 2e-3 * adj.abs().max(fd.abs()) + floor,
        "{what}: adjoint {adj:.6e} vs finite difference {fd:.6e}"
    );
}

#[test]
fn texel_gradients_match_finite_differences_at_the_poles_and_across_the_seam() {
    let f = Fixture::new();
    let trace = TraceScene::new(&f.scene);
    let placed = trace.place_state(&f.scene.states[0]);
    let map = EnvMap::new(&f.env, ROTATION);
    let paths = replays(&placed, &f.scene, &map);
    let (texels, _) = adjoint(&paths, &placed, &f.scene, &map);
    let j0 = objective(&paths, &f.scene, &f.env).abs();
    let eps = 1e-3f32;
    // Every texel of the top and bottom rows (poles; the two ends of a row meet at the seam)
    // and a column's worth in between.
    let mut which: Vec<usize> = (0..ENV_W)
        .chain((ENV_H - 1) * ENV_W..ENV_H * ENV_W)
        .collect();
    which.extend((1..ENV_H - 1).map(|y| y * ENV_W + (y * 5) % ENV_W));
    let mut nonzero = 0;
    for &i in &which {
        for c in 0..3 {
            let mut up = f.env.clone();
            let mut dn = f.env.clone();
            let v = up.pixels[i][c];
            up.pixels[i][c] = v + eps;
            dn.pixels[i][c] = v - eps;
            let fd = (objective(&paths, &f.scene, &up) - objective(&paths, &f.scene, &dn))
                / (2.0 * eps as f64);
            agree(
                texels[i][c],
                fd,
                1e-4 * j0,
                &format!("texel {i} channel {c}"),
            );
            nonzero += (texels[i][c].abs() > 1e-3) as u32;
        }
    }
    assert!(nonzero > 30, "the test should read many texels: {nonzero}");
    // Not the adjoint of something else: the planted error (a texel off by one column)
    // would be caught.
    let wrong = texels[1][0];
    let mut up = f.env.clone();
    let mut dn = f.env.clone();
    up.pixels[0][0] += eps;
    dn.pixels[0][0] -= eps;
    let fd0 =
        (objective(&paths, &f.scene, &up) - objective(&paths, &f.scene, &dn)) / (2.0 * eps as f64);
    assert!(
        (wrong - fd0).abs() > 2e-3 * fd0.abs() + 1e-4 * j0,
        "a planted error slips through"
    );
}

/// The surfels with the largest |gradient| of one kind, and a few others that are hit.
fn pick(g: &[f32], n: usize) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..g.len()).filter(|&i| g[i] != 0.0).collect();
    idx.sort_by(|&a, &b| g[b].abs().total_cmp(&g[a].abs()));
    let mut out: Vec<usize> = idx.iter().take(n).copied().collect();
    out.extend(idx.iter().step_by((idx.len() / n).max(1)).take(n).copied());
    out.sort();
    out.dedup();
    out
}

/// Checks the material gradients `grads` of `paths`' replayed objective against central
/// differences of it, on the 4 surfels of each component with the largest gradients in each of
/// base colour (every channel), metallic and roughness (ε = 1e-3; the floor, 2e-4 of J, is J's
/// f32 rounding over ~10³ terms divided by 2ε). Returns how many were checked.
fn check_materials_by_finite_differences(
    f: &Fixture,
    paths: &[(PathReplay, [f32; 3])],
    grads: &TraceGradients,
    what: &str,
) -> usize {
    let j0 = objective(paths, &f.scene, &f.env).abs();
    let eps = 1e-3f32;
    let mut checked = 0;
    for comp in 0..f.scene.components.len() {
        let g = &grads.surfels[comp];
        let central = |set: &dyn Fn(&mut Surfels, f32)| {
            let mut up = f.scene.clone();
            let mut dn = f.scene.clone();
            set(&mut up.components[comp].surfels, eps);
            set(&mut dn.components[comp].surfels, -eps);
            (objective(paths, &up, &f.env) - objective(paths, &dn, &f.env)) / (2.0 * eps as f64)
        };
        let mut check = |adj: f32, fd: f64, which: String| {
            agree(
                adj as f64,
                fd,
                2e-4 * j0,
                &format!("{what}: component {comp} surfel {which}"),
            );
            checked += 1;
        };
        let bc: Vec<f32> = g.base_color.iter().map(|v| v[1]).collect();
        for i in pick(&bc, 4) {
            for c in 0..3 {
                let fd = central(&|s, e| s.base_color[i][c] += e);
                check(g.base_color[i][c], fd, format!("{i} base colour {c}"));
            }
        }
        for i in pick(&g.metallic, 4) {
            let fd = central(&|s, e| s.metallic[i] += e);
            check(g.metallic[i], fd, format!("{i} metallic"));
        }
        for i in pick(&g.roughness, 4) {
            let fd = central(&|s, e| s.roughness[i] += e);
            check(g.roughness[i], fd, format!("{i} roughness"));
        }
    }
    checked
}

/// ⟨ȳ, J v⟩ = ⟨Jᵀ ȳ, v⟩ in the texels for a random map v (seed `seed`): J v is the replayed
/// estimate of v itself (the estimate is linear in the texels), so the identity is exact up to
/// f32 rounding (1e-4 relative).
fn check_texel_dot_product(
    f: &Fixture,
    paths: &[(PathReplay, [f32; 3])],
    texels: &[[f64; 3]],
    seed: u64,
) {
    let v = random_env(ENV_W, ENV_H, seed, 1.0);
    let jv = objective(paths, &f.scene, &v);
    let jt: f64 = (0..ENV_W * ENV_H)
        .map(|i| {
            (0..3)
                .map(|c| texels[i][c] * v.pixels[i][c] as f64)
                .sum::<f64>()
        })
        .sum();
    assert!(
        (jv - jt).abs() <= 1e-4 * jv.abs().max(jt.abs()),
        "texels (map {seed}): {jv} vs {jt}"
    );
}

#[test]
fn material_gradients_match_finite_differences() {
    let f = Fixture::new();
    let trace = TraceScene::new(&f.scene);
    let placed = trace.place_state(&f.scene.states[0]);
    let map = EnvMap::new(&f.env, ROTATION);
    let paths = replays(&placed, &f.scene, &map);
    let (_, grads) = adjoint(&paths, &placed, &f.scene, &map);
    let checked = check_materials_by_finite_differences(&f, &paths, &grads, "1 bounce");
    assert!(checked >= 30, "{checked}");
}

#[test]
fn dot_product_identity() {
    // ⟨ȳ, J v⟩ = ⟨Jᵀ ȳ, v⟩ for random directions v: in the texels J v is the replayed estimate of
    // the map v itself (linearity), exact; in every surfel's material J v is a central
    // difference along v.
    let f = Fixture::new();
    let trace = TraceScene::new(&f.scene);
    let placed = trace.place_state(&f.scene.states[0]);
    let map = EnvMap::new(&f.env, ROTATION);
    let paths = replays(&placed, &f.scene, &map);
    let (texels, grads) = adjoint(&paths, &placed, &f.scene, &map);
    let mut rng = SplitMix(21);
    for trial in 0..3 {
        check_texel_dot_product(&f, &paths, &texels, 100 + trial);

        let dirs: Vec<Vec<[f32; 5]>> = f
            .scene
            .components
            .iter()
            .map(|c| {
                (0..c.surfels.len())
                    .map(|_| [0; 5].map(|_: i32| rng.f32() - 0.5))
                    .collect()
            })
            .collect();
        // ε = 1e-2: J's f32 rounding over ~10³ terms (~1e-6 of J) divided by 2ε stays below
        // 1e-3 of J'v, and J is affine in colour and metallic, smooth in roughness (r ≥ 0.2).
        let eps = 1e-2f32;
        let moved = |s: f32| {
            let mut sc = f.scene.clone();
            for (comp, d) in sc.components.iter_mut().zip(&dirs) {
                for (i, v) in d.iter().enumerate() {
                    for c in 0..3 {
                        comp.surfels.base_color[i][c] += s * v[c];
                    }
                    comp.surfels.metallic[i] += s * v[3];
                    comp.surfels.roughness[i] += s * v[4];
                }
            }
            sc
        };
        let jv = (objective(&paths, &moved(eps), &f.env) - objective(&paths, &moved(-eps), &f.env))
            / (2.0 * eps as f64);
        let mut jt = 0.0f64;
        for (g, d) in grads.surfels.iter().zip(&dirs) {
            for (i, v) in d.iter().enumerate() {
                for c in 0..3 {
                    jt += g.base_color[i][c] as f64 * v[c] as f64;
                }
                jt += g.metallic[i] as f64 * v[3] as f64 + g.roughness[i] as f64 * v[4] as f64;
            }
        }
        assert!(
            (jv - jt).abs() <= 2e-3 * jv.abs().max(jt.abs()),
            "materials: {jv} vs {jt}"
        );
    }
}

#[test]
fn a_path_that_contributes_nothing_gets_no_gradient() {
    let f = Fixture::new();
    let trace = TraceScene::new(&f.scene);
    let placed = trace.place_state(&f.scene.states[0]);
    // A black environment lights nothing: every path's radiance is zero, so no material gets
    // gradient (the texels still do: lighting would change the image).
    let black = EnvMap::new(
        &Environment::constant("black", ENV_W, ENV_H, [0.0; 3]),
        ROTATION,
    );
    let paths = replays(&placed, &f.scene, &black);
    let (texels, grads) = adjoint(&paths, &placed, &f.scene, &black);
    for g in &grads.surfels {
        assert!(g.base_color.iter().all(|v| *v == [0.0; 3]));
        assert!(g.metallic.iter().chain(&g.roughness).all(|v| *v == 0.0));
    }
    assert!(texels.iter().any(|t| t.iter().any(|v| *v != 0.0)));
    // A camera ray that misses the scene reads four texels and nothing else.
    let map = EnvMap::new(&f.env, ROTATION);
    let est = Estimator::new(
        &placed,
        &map,
        self_hit_epsilon(&f.scene, &f.scene.states[0]),
    );
    let up = [0.0f32, 1.0, 0.0];
    let p = est.replay([0.0, 5.0, 0.0], up, &Sampler::new(0, 0), 0);
    assert_eq!(p.record.hits, 0);
    let mut read = Vec::new();
    let mg = p.adjoint(&map, [1.0, 2.0, 3.0], |i, _| read.push(i));
    assert_eq!(mg, [MaterialGrad::default(); 2]);
    assert!(read.len() <= 4 && !read.is_empty());
    assert!(p.record_grads(&mg).iter().all(|r| r.is_none()));
    // And ȳ = 0 sends nothing anywhere.
    let paths = replays(&placed, &f.scene, &map);
    for (p, _) in paths.iter().take(50) {
        let mut any = false;
        let mg = p.adjoint(&map, [0.0; 3], |_, _| any = true);
        assert!(!any && mg == [MaterialGrad::default(); 2]);
    }
}

#[test]
fn naive_estimator_replays_and_differentiates_too() {
    // Table 4's baseline goes through the same terms: forward = replay, and its material
    // gradients match finite differences of the replayed estimate.
    let f = Fixture::new();
    let trace = TraceScene::new(&f.scene);
    let placed = trace.place_state(&f.scene.states[0]);
    let map = EnvMap::new(&f.env, ROTATION);
    let paths = replays_with(&placed, &f.scene, &map, Strategy::Naive);
    assert!(paths
        .iter()
        .any(|(p, _)| p.terms().iter().any(|t| t.secondary.is_some())));
    for (p, _) in &paths {
        assert!(p.terms().iter().all(|t| t.primary.is_none()
            || t.env_dir == t.secondary.map_or(t.primary.unwrap().wi, |b| b.wi)));
    }
    let (texels, grads) = adjoint(&paths, &placed, &f.scene, &map);
    let j0 = objective(&paths, &f.scene, &f.env).abs();
    let eps = 1e-3f32;
    for i in [0usize, ENV_W - 1, 3 * ENV_W + 5] {
        let mut up = f.env.clone();
        let mut dn = f.env.clone();
        up.pixels[i][1] += eps;
        dn.pixels[i][1] -= eps;
        let fd = (objective(&paths, &f.scene, &up) - objective(&paths, &f.scene, &dn))
            / (2.0 * eps as f64);
        agree(texels[i][1], fd, 1e-4 * j0, &format!("naive texel {i}"));
    }
    let g = &grads.surfels[1];
    for i in pick(&g.roughness, 3) {
        let mut up = f.scene.clone();
        let mut dn = f.scene.clone();
        up.components[1].surfels.roughness[i] += eps;
        dn.components[1].surfels.roughness[i] -= eps;
        let fd =
            (objective(&paths, &up, &f.env) - objective(&paths, &dn, &f.env)) / (2.0 * eps as f64);
        agree(
            g.roughness[i] as f64,
            fd,
            2e-4 * j0,
            &format!("naive roughness {i}"),
        );
    }
}

#[test]
fn deeper_vertices_replay_and_differentiate() {
    // With 3 bounces (not in the paper) a path adds next-event terms past the secondary
    // record whose deeper factors are frozen in the tail: forward = replay, the replayed
    // estimate stays linear in the texels (so the texel adjoint is exact: dot-product
    // identity), and the gradients of the first two records' materials match finite
    // differences of the replayed estimate (the tail held, as the adjoint holds it).
    let f = Fixture::new();
    let trace = TraceScene::new(&f.scene);
    let placed = trace.place_state(&f.scene.states[0]);
    let map = EnvMap::new(&f.env, ROTATION);
    // 16 spp: paths that reach a third record are a few per cent of this open scene's.
    let paths = replays_bounces(&placed, &f.scene, &map, Strategy::Full, 3, 16);
    let deep = paths
        .iter()
        .flat_map(|(p, _)| p.terms())
        .filter(|t| t.tail != [1.0; 3])
        .count();
    assert!(deep >= 30, "only {deep} terms past the secondary record");
    let est = Estimator::new(
        &placed,
        &map,
        self_hit_epsilon(&f.scene, &f.scene.states[0]),
    )
    .with_bounces(3);
    let cam = camera(Vec3::new(0.2, -0.05, 1.7), 12, 12, 7.0);
    for y in 0..12 {
        for x in 0..12 {
            let (o, d) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
            let s = Sampler::new(y * 12 + x, 1);
            for i in 0..2 {
                let p = est.replay(o, d, &s, i);
                assert_eq!(est.radiance(o, d, &s, i).radiance, p.radiance(&map));
                assert_eq!(p.radiance_with(&p.materials, &map), p.radiance(&map));
            }
        }
    }
    let (texels, grads) = adjoint(&paths, &placed, &f.scene, &map);
    check_texel_dot_product(&f, &paths, &texels, 300);
    let checked = check_materials_by_finite_differences(&f, &paths, &grads, "3 bounces");
    assert!(checked >= 30, "{checked}");
}
