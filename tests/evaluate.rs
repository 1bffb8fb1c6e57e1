//! The pieces of `lightfuse evaluate` (`eval::relight`): shared primary records
//! (`shade::render::Primaries`), the No re-tracing estimator (`Strategy::Unshadowed`) and the
//! albedo rescale by re-evaluated paths. The end-to-end run is `blender/tests/test_evaluate.py`.
//!
//! Tolerances. Primaries against `render_image` and Unshadowed against Full on a scene with
//! nothing to occlude or inter-reflect are exact: the same (pixel, sample, seed) draws the same
//! numbers and the same terms, so only f32 arithmetic order could differ, and it does not. The
//! rescale is compared with a render of the scene whose base colours were scaled: both are
//! unbiased estimates that draw their lobes from different materials, so they agree in the
//! image mean to Monte Carlo noise; 1.5 % is ~4 standard errors of that mean, measured from the
//! per-pixel differences.

use glam::Vec3;
use lightfuse::scene::{Environment, Scene};
use lightfuse::shade::estimator::{self_hit_epsilon, Estimator, PixelFilter, Strategy};
use lightfuse::shade::render::{render_image, Primaries};
use lightfuse::shade::EnvMap;
use lightfuse::trace::TraceScene;

mod common;
use common::surfel_scenes::{camera, floor, mat, random_env, scene_of, sphere};

fn ball_on_floor() -> Scene {
    scene_of(vec![
        floor(-0.5, 2.0, 0.04, mat([0.6, 0.5, 0.4], 0.0, 0.7)),
        sphere(Vec3::ZERO, 0.5, 3000, mat([0.8, 0.3, 0.2], 0.5, 0.3)),
    ])
}

#[test]
fn primaries_shade_exactly_the_image_render_image_draws() {
    let scene = ball_on_floor();
    let trace = TraceScene::new(&scene);
    let placed = trace.place_state(&scene.states[0]);
    let env = EnvMap::new(&random_env(32, 16, 7, 1.0), 30.0);
    let est = Estimator::new(&placed, &env, self_hit_epsilon(&scene, &scene.states[0]));
    let cam = camera(Vec3::new(0.0, 0.3, 3.0), 24, 16, 20.0);
    let filter = PixelFilter::new(1.5);
    let (image, _) = render_image(&est, &filter, &cam, 4, 11, &|_| {});
    let p = Primaries::trace(&placed, &filter, &cam, 4, 11);
    let (shaded, rays) = p.shade(&est, &[[1.0; 3]]);
    assert_eq!(
        shaded[0], image.radiance,
        "the same paths, the same radiance"
    );
    assert!(rays > 0);
    let aovs = p.aovs();
    assert_eq!(aovs.alpha, image.aovs.alpha);
    assert_eq!(aovs.depth, image.aovs.depth);
    assert_eq!(aovs.normal, image.aovs.normal);
    assert_eq!(aovs.albedo, image.aovs.albedo);
    assert!(aovs.depth.iter().any(|&z| z > 0.0) && aovs.depth.contains(&0.0));
}

#[test]
fn unshadowed_is_full_without_occluders_and_ignores_them_with() {
    let m = mat([0.6, 0.5, 0.4], 0.2, 0.5);
    let alone = scene_of(vec![floor(-0.5, 2.0, 0.04, m)]);
    let covered = scene_of(vec![
        floor(-0.5, 2.0, 0.04, m),
        // A roof over the floor, out of the camera's view: it shadows everything.
        floor(1.5, 3.0, 0.04, mat([0.5; 3], 0.0, 1.0)),
    ]);
    let env = EnvMap::new(&random_env(32, 16, 3, 1.0), 0.0);
    // Narrow enough (±11° vertically) that the roof stays out of view.
    let cam = camera(Vec3::new(0.0, -0.2, 3.0), 16, 12, 30.0);
    let filter = PixelFilter::new(0.0);
    let render = |scene: &Scene, strategy: Strategy| {
        let trace = TraceScene::new(scene);
        let placed = trace.place_state(&scene.states[0]);
        let est = Estimator::new(&placed, &env, self_hit_epsilon(scene, &scene.states[0]))
            .with_strategy(strategy);
        let p = Primaries::trace(&placed, &filter, &cam, 8, 5);
        let (img, rays) = p.shade(&est, &[[1.0; 3]]);
        (img.into_iter().next().unwrap(), rays, p.aovs().alpha)
    };
    let (full, _, alpha) = render(&alone, Strategy::Full);
    let (unshadowed, rays, _) = render(&alone, Strategy::Unshadowed);
    assert!(
        alpha.iter().filter(|&&a| a > 0.9).count() > 40,
        "the camera sees the floor"
    );
    assert!(
        unshadowed == full,
        "nothing occludes or inter-reflects: the same terms"
    );
    assert_eq!(
        rays, 0,
        "No re-tracing traces nothing after the primary hit"
    );
    let (under_roof, _, _) = render(&covered, Strategy::Unshadowed);
    assert!(
        under_roof == full,
        "the roof is not seen by the unshadowed estimator"
    );
    let (shadowed, _, _) = render(&covered, Strategy::Full);
    let sum = |img: &[[f32; 3]]| {
        img.iter()
            .zip(&alpha)
            .filter(|(_, &a)| a > 0.9)
            .map(|(p, _)| p[0] as f64)
            .sum::<f64>()
    };
    assert!(
        sum(&shadowed) < 0.8 * sum(&full),
        "the full estimator sees the roof's shadow"
    );
}

#[test]
fn rescaled_base_colour_matches_a_render_of_the_rescaled_scene() {
    let scale = [1.3, 0.8, 1.0];
    let base = [0.5, 0.6, 0.4];
    let make = |b: [f32; 3]| {
        scene_of(vec![
            floor(-0.5, 2.0, 0.04, mat(b, 0.0, 0.6)),
            sphere(Vec3::new(0.0, 0.0, 0.0), 0.5, 3000, mat(b, 0.0, 0.4)),
        ])
    };
    let scaled_base = [0, 1, 2].map(|c| base[c] * scale[c]);
    let (scene, target) = (make(base), make(scaled_base));
    let env = EnvMap::new(&Environment::constant("grey", 32, 16, [1.0; 3]), 0.0);
    let cam = camera(Vec3::new(0.0, 0.2, 3.0), 24, 16, 16.0);
    let filter = PixelFilter::new(0.0);
    let shade = |s: &Scene, scales: &[[f32; 3]]| {
        let trace = TraceScene::new(s);
        let placed = trace.place_state(&s.states[0]);
        let est = Estimator::new(&placed, &env, self_hit_epsilon(s, &s.states[0]));
        Primaries::trace(&placed, &filter, &cam, 64, 2)
            .shade(&est, scales)
            .0
    };
    let rescaled = shade(&scene, &[[1.0; 3], scale]);
    let truth = shade(&target, &[[1.0; 3]]);
    // Surface pixels only: the environment behind is not rescaled.
    let covered: Vec<bool> = {
        let trace = TraceScene::new(&scene);
        let placed = trace.place_state(&scene.states[0]);
        let p = Primaries::trace(&placed, &filter, &cam, 64, 2);
        p.aovs().alpha.iter().map(|&a| a > 0.99).collect()
    };
    assert!(covered.iter().filter(|&&c| c).count() > 100);
    let sum = |img: &[[f32; 3]], c: usize| -> f64 {
        img.iter()
            .zip(&covered)
            .filter(|(_, &k)| k)
            .map(|(p, _)| p[c] as f64)
            .sum()
    };
    for (c, &k) in scale.iter().enumerate() {
        let (a, b, raw) = (
            sum(&rescaled[1], c),
            sum(&truth[0], c),
            sum(&rescaled[0], c),
        );
        assert!((a / b - 1.0).abs() < 0.015, "channel {c}: {a} vs {b}");
        if k != 1.0 {
            assert!(
                (raw / b - 1.0).abs() > 0.1,
                "channel {c}: the rescale changes something"
            );
        }
    }
}

/// `eval::shadows::lit_share`: a sun (one bright texel 19.7° from the zenith, ~93 % of a
/// horizontal point's light) over a dim uniform sky, and an opaque 1 × 1 square one unit above
/// a point. The point keeps exactly the light from the directions that miss the square; a
/// point far to the side keeps all of it.
#[test]
fn the_lit_share_of_a_point_under_a_square_is_the_light_it_still_sees() {
    use lightfuse::eval::shadows::{lit_share, LIT, SAMPLES, SHADOWED};
    let (w, h) = (64, 32);
    let mut px = vec![[0.2f32; 3]; w * h];
    px[2 * w + w / 2] = [4000.0; 3];
    let env = Environment::new("sun", w, h, px);
    let map = EnvMap::new(&env, 0.0);
    let scene = scene_of(vec![floor(1.0, 0.5, 0.02, mat([0.5; 3], 0.0, 0.5))]);
    let trace = TraceScene::new(&scene);
    let placed = trace.place_state(&scene.states[0]);
    let n = Vec3::Y;
    // The exact share from the texels: a texel's light is blocked when its centre direction
    // meets the square (|x / y| and |z / y| within 0.5 at y = 1).
    let (mut all, mut kept) = (0.0f64, 0.0f64);
    for y in 0..h {
        for x in 0..w {
            let d = lightfuse::shade::envmap::uv_to_direction([
                (x as f32 + 0.5) / w as f32,
                (y as f32 + 0.5) / h as f32,
            ]);
            let c = n.dot(d).max(0.0) as f64;
            let l = env.pixels[y * w + x][0] as f64 * c * env.texel_solid_angle(y);
            all += l;
            if !(d.y > 0.0 && (d.x / d.y).abs() < 0.5 && (d.z / d.y).abs() < 0.5) {
                kept += l;
            }
        }
    }
    let exact = (kept / all) as f32;
    assert!(exact < 0.1, "the sun carries most of the light: {exact}");
    // The estimate over seeds: its mean within 3 standard errors of the exact share (a share
    // of SAMPLES draws, most of them the sun's: binomial, σ ≤ 0.5 / √SAMPLES per estimate).
    let seeds = 32;
    let est: Vec<f32> = (0..seeds)
        .map(|s| lit_share(&placed, &map, Vec3::ZERO, n, 1e-4, s).unwrap())
        .collect();
    let mean = est.iter().sum::<f32>() / seeds as f32;
    let tol = 3.0 * 0.5 / ((SAMPLES * seeds as usize) as f32).sqrt();
    assert!((mean - exact).abs() < tol, "{mean} vs {exact} ± {tol}");
    assert!(est.iter().all(|&s| s < SHADOWED), "{est:?}");
    // Out from under the square: every direction above the surface reaches the sky.
    let open = lit_share(&placed, &map, Vec3::new(5.0, 0.0, 0.0), n, 1e-4, 3).unwrap();
    assert_eq!(open, 1.0);
    assert!(open > LIT);
    // A point facing away from every drawn direction has no light to share.
    let dark = Environment::new("down", w, h, {
        let mut p = vec![[0.0f32; 3]; w * h];
        p[(h - 1) * w] = [1.0; 3]; // only the nadir's row
        p
    });
    let down = EnvMap::new(&dark, 0.0);
    assert_eq!(
        lit_share(&placed, &down, Vec3::new(5.0, 0.0, 0.0), n, 1e-4, 3),
        None
    );
}
