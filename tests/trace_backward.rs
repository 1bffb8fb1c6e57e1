//! The ray tracer's backward pass (`Placed::composite_backward`) against central differences of
//! its f64 brute-force reference (`trace::reference::composite_ref`).
//!
//! Tolerances, and why:
//! - Every check compares dL/dθ for L = Σ_rays ⟨ȳ, record⟩ with random upstream gradients ȳ
//!   (the shape a loss hands the backward pass). Differences are taken in f64 with h = 1e-6:
//!   truncation ~h², round-off ~1e-16·|L|/h ≈ 1e-9, far below the f32 backward's own error.
//! - The backward works in f32: hit geometry is recomputed from the stored parameters, the
//!   transmittance is recovered by division (α ≤ 0.99), and a parameter's gradient is a sum over
//!   rays and hits with cancellation. Its error is relative (~1e-5) plus absolute noise
//!   proportional to the largest gradient of the same kind. Accepted:
//!   |analytic − fd| ≤ 1e-3 |fd| + 1e-3 · max|fd| over that parameter kind; the worst ratio seen
//!   is printed by each test (well under 0.1 of the allowance on random scenes). A planted 1%
//!   error in the largest gradient of each kind, or a flipped sign, must be caught
//!   (`planted_errors_are_caught`), so the comparison can fail.
//! - The composite is piecewise smooth: a hit appears or vanishes at the support edge and at
//!   α = MIN_ALPHA, the T_MIN stop moves, coplanar ties swap order. The backward holds the hit
//!   set fixed (module doc of `trace::backward`), so a difference straddling a jump is not a
//!   derivative. We detect it instead of hand-picking parameters: differences with h and h/2 must
//!   agree to 1e-4 relative (a jump within h makes them differ by a factor ~2), otherwise the
//!   parameter is skipped; at most 3% may be skipped, which each test asserts.
//! - In the coplanar case, moving a plane along its normal (position along n, rotations, the
//!   placement's out-of-plane parts) reorders the tied hits: a kink that central differences
//!   average over. Those parameters are left out of that one test; the in-plane ones are checked.
//! - Chain rules of the record's means are checked in f32 with h = 1e-3 on values ~1:
//!   round-off ~1e-7/1e-3 = 1e-4, so 2e-3 of the largest gradient is allowed.

use glam::Vec3;
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::{Rigid, Surfels};
use lightfuse::trace::reference::{composite_ref, RefComponent};
use lightfuse::trace::{
    RecordGrad, SurfaceRecord, TraceGradients, TraceRay, TraceScene, CUTOFF, RAY_CHUNK,
};

mod common;
use common::push;

/// A scene, its placement, rays and the upstream gradient of each ray's record.
struct Case {
    components: Vec<Surfels>,
    transforms: Vec<Rigid>,
    rays: Vec<TraceRay>,
    grads: Vec<RecordGrad>,
}

fn random_grad(rng: &mut SplitMix) -> RecordGrad {
    let mut r = || rng.range(-1.0, 1.0);
    RecordGrad {
        depth: r(),
        position: [r(), r(), r()],
        normal: [r(), r(), r()],
        base_color: [r(), r(), r()],
        metallic: r(),
        roughness: r(),
        alpha: r(),
    }
}

fn grad_vec(g: &RecordGrad) -> [f64; 13] {
    let (p, n, a) = (g.position, g.normal, g.base_color);
    [
        g.depth,
        p[0],
        p[1],
        p[2],
        n[0],
        n[1],
        n[2],
        a[0],
        a[1],
        a[2],
        g.metallic,
        g.roughness,
        g.alpha,
    ]
    .map(f64::from)
}

fn ray(o: Vec3, d: Vec3) -> TraceRay {
    TraceRay {
        origin: o.to_array(),
        dir: d.normalize().to_array(),
        t_min: 0.0,
        t_max: f32::INFINITY,
    }
}

/// Tens of surfels in three components (one at identity, two under random rigid transforms),
/// large enough that rays cross several layers.
fn random_case(seed: u64, rays: usize) -> Case {
    let mut rng = SplitMix(seed);
    let mut components = Vec::new();
    for n in [24, 18, 18] {
        let mut s = Surfels::with_sh_degree(0);
        for _ in 0..n {
            let mu = [0; 3].map(|_| rng.range(-0.5, 0.5));
            let q = rng.unit_quat();
            let scale = [rng.range(0.15, 0.4), rng.range(0.15, 0.4)];
            let a = rng.range(0.2, 0.95);
            let c = rng.f32();
            push(&mut s, mu, q, scale, a, c);
        }
        components.push(s);
    }
    let mut transforms = vec![Rigid::IDENTITY];
    for _ in 0..2 {
        transforms.push(Rigid {
            rotation: rng.unit_quat(),
            translation: [0; 3].map(|_| rng.range(-0.2, 0.2)),
        });
    }
    let rays: Vec<TraceRay> = (0..rays)
        .map(|_| {
            let o = Vec3::new(
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            )
            .normalize()
                * 3.0;
            let target = Vec3::new(
                rng.range(-0.3, 0.3),
                rng.range(-0.3, 0.3),
                rng.range(-0.3, 0.3),
            );
            ray(o, target - o)
        })
        .collect();
    let grads = rays.iter().map(|_| random_grad(&mut rng)).collect();
    Case {
        components,
        transforms,
        rays,
        grads,
    }
}

fn backward(case: &Case) -> TraceGradients {
    let parts: Vec<&Surfels> = case.components.iter().collect();
    let scene = TraceScene::from_components(&parts);
    scene
        .place(&case.transforms)
        .composite_backward(&parts, &case.rays, &case.grads, true)
}

fn forward(case: &Case) -> Vec<SurfaceRecord> {
    let parts: Vec<&Surfels> = case.components.iter().collect();
    let scene = TraceScene::from_components(&parts);
    let placed = scene.place(&case.transforms);
    case.rays
        .iter()
        .map(|r| placed.composite(r.origin, r.dir, r.t_min, r.t_max))
        .collect()
}

fn refs(case: &Case) -> Vec<RefComponent> {
    case.components
        .iter()
        .zip(&case.transforms)
        .map(|(s, tf)| RefComponent::new(s, tf))
        .collect()
}

/// L = Σ_rays ⟨ȳ, record⟩ from the f64 reference.
fn loss(case: &Case, refs: &[RefComponent]) -> f64 {
    case.rays
        .iter()
        .zip(&case.grads)
        .map(|(r, g)| {
            let rec = composite_ref(
                refs,
                r.origin.map(f64::from),
                r.dir.map(f64::from),
                r.t_min as f64,
                r.t_max as f64,
            );
            rec.sums()
                .iter()
                .zip(grad_vec(g))
                .map(|(a, b)| a * b)
                .sum::<f64>()
        })
        .sum()
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Position,
    Rotation,
    Scale,
    Opacity,
    BaseColor,
    Metallic,
    Roughness,
    Translation,
    Omega,
}

const KINDS: [Kind; 9] = [
    Kind::Position,
    Kind::Rotation,
    Kind::Scale,
    Kind::Opacity,
    Kind::BaseColor,
    Kind::Metallic,
    Kind::Roughness,
    Kind::Translation,
    Kind::Omega,
];

/// One scalar parameter: kind, component, surfel (unused for placements), coordinate.
#[derive(Clone, Copy, Debug)]
struct Param(Kind, usize, usize, usize);

fn params(case: &Case) -> Vec<Param> {
    let mut out = Vec::new();
    for (c, s) in case.components.iter().enumerate() {
        for kind in KINDS {
            let dims = match kind {
                Kind::Position | Kind::BaseColor | Kind::Translation | Kind::Omega => 3,
                Kind::Rotation => 4,
                Kind::Scale => 2,
                _ => 1,
            };
            let count = match kind {
                Kind::Translation | Kind::Omega => 1,
                _ => s.len(),
            };
            for i in 0..count {
                for k in 0..dims {
                    out.push(Param(kind, c, i, k));
                }
            }
        }
    }
    out
}

fn analytic(g: &TraceGradients, p: Param) -> f64 {
    let Param(kind, c, i, k) = p;
    let s = &g.surfels[c];
    (match kind {
        Kind::Position => s.position[i][k],
        Kind::Rotation => s.rotation[i][k],
        Kind::Scale => s.scale[i][k],
        Kind::Opacity => s.opacity[i],
        Kind::BaseColor => s.base_color[i][k],
        Kind::Metallic => s.metallic[i],
        Kind::Roughness => s.roughness[i],
        Kind::Translation => g.transforms[c].translation[k],
        Kind::Omega => g.transforms[c].rotation[k],
    }) as f64
}

fn set_analytic(g: &mut TraceGradients, p: Param, v: f32) {
    let Param(kind, c, i, k) = p;
    let s = &mut g.surfels[c];
    match kind {
        Kind::Position => s.position[i][k] = v,
        Kind::Rotation => s.rotation[i][k] = v,
        Kind::Scale => s.scale[i][k] = v,
        Kind::Opacity => s.opacity[i] = v,
        Kind::BaseColor => s.base_color[i][k] = v,
        Kind::Metallic => s.metallic[i] = v,
        Kind::Roughness => s.roughness[i] = v,
        Kind::Translation => g.transforms[c].translation[k] = v,
        Kind::Omega => g.transforms[c].rotation[k] = v,
    }
}

/// Adds `h` to one parameter of the f64 reference (a placement by its left increment).
fn nudge(refs: &mut [RefComponent], p: Param, h: f64) {
    let Param(kind, c, i, k) = p;
    let r = &mut refs[c];
    let mut e = [0.0; 3];
    match kind {
        Kind::Position => r.position[i][k] += h,
        Kind::Rotation => r.rotation[i][k] += h,
        Kind::Scale => r.scale[i][k] += h,
        Kind::Opacity => r.opacity[i] += h,
        Kind::BaseColor => r.base_color[i][k] += h,
        Kind::Metallic => r.metallic[i] += h,
        Kind::Roughness => r.roughness[i] += h,
        Kind::Translation => {
            e[k] = h;
            r.perturb(e, [0.0; 3]);
        }
        Kind::Omega => {
            e[k] = h;
            r.perturb([0.0; 3], e);
        }
    }
}

const H: f64 = 1e-6;

fn central(case: &Case, base: &[RefComponent], p: Param, h: f64) -> f64 {
    let mut plus = base.to_vec();
    nudge(&mut plus, p, h);
    let mut minus = base.to_vec();
    nudge(&mut minus, p, -h);
    (loss(case, &plus) - loss(case, &minus)) / (2.0 * h)
}

/// Central differences of every selected parameter, `None` where h and h/2 disagree (a jump).
fn differences(case: &Case, select: &dyn Fn(Param) -> bool) -> Vec<(Param, Option<f64>)> {
    let base = refs(case);
    params(case)
        .into_iter()
        .filter(|&p| select(p))
        .map(|p| {
            let a = central(case, &base, p, H);
            let b = central(case, &base, p, H / 2.0);
            let smooth = (a - b).abs() <= 1e-4 * a.abs().max(b.abs()) + 1e-7;
            (p, smooth.then_some(b))
        })
        .collect()
}

const REL: f64 = 1e-3;
const ABS: f64 = 1e-3;

/// What a comparison found: mismatches, skipped parameters, and the worst error as a fraction
/// of its allowance.
#[derive(Debug, Default)]
struct Report {
    failures: Vec<String>,
    skipped: usize,
    compared: usize,
    worst: f64,
}

fn compare(g: &TraceGradients, fd: &[(Param, Option<f64>)]) -> Report {
    let mut r = Report::default();
    for kind in KINDS {
        let of_kind: Vec<(Param, f64)> = fd
            .iter()
            .filter(|(p, _)| p.0 == kind)
            .filter_map(|&(p, v)| v.map(|v| (p, v)))
            .collect();
        let max = of_kind.iter().map(|(_, v)| v.abs()).fold(0.0, f64::max);
        for (p, v) in of_kind {
            let a = analytic(g, p);
            let allowed = REL * v.abs() + ABS * max + 1e-9;
            let ratio = (a - v).abs() / allowed;
            r.worst = r.worst.max(ratio);
            r.compared += 1;
            // NaN counts as a failure.
            if ratio.is_nan() || ratio > 1.0 {
                r.failures
                    .push(format!("{p:?}: backward {a:e} vs fd {v:e} (max {max:e})"));
            }
        }
    }
    r.skipped = fd.iter().filter(|(_, v)| v.is_none()).count();
    r
}

fn assert_matches(what: &str, g: &TraceGradients, fd: &[(Param, Option<f64>)]) -> Report {
    let r = compare(g, fd);
    println!(
        "{what}: {} compared, {} skipped, worst error {:.3} of the allowance",
        r.compared, r.skipped, r.worst
    );
    assert!(
        r.failures.is_empty(),
        "{what}: {} mismatches:\n{}",
        r.failures.len(),
        r.failures.join("\n")
    );
    assert!(
        r.skipped * 100 <= 3 * fd.len(),
        "{what}: {} of {} parameters straddle a jump",
        r.skipped,
        fd.len()
    );
    r
}

fn all(_: Param) -> bool {
    true
}

#[test]
fn gradients_match_central_differences_on_random_scenes() {
    for seed in [1, 2] {
        let case = random_case(seed, 24);
        let records = forward(&case);
        let hits: u32 = records.iter().map(|r| r.hits).sum();
        assert!(
            hits as usize >= 3 * case.rays.len(),
            "seed {seed}: rays should cross several layers ({hits} hits)"
        );
        let g = backward(&case);
        let fd = differences(&case, &all);
        // Every kind must have been exercised with non-zero gradients.
        for kind in KINDS {
            assert!(
                fd.iter()
                    .any(|(p, v)| p.0 == kind && v.is_some_and(|v| v.abs() > 1e-3)),
                "seed {seed}: no {kind:?} gradient to compare"
            );
        }
        assert_matches(&format!("random scene {seed}"), &g, &fd);
    }
}

#[test]
fn planted_errors_are_caught() {
    let case = random_case(1, 24);
    let g = backward(&case);
    let fd = differences(&case, &all);
    assert!(compare(&g, &fd).failures.is_empty());
    for kind in KINDS {
        let Some(&(p, _)) = fd
            .iter()
            .filter(|(p, v)| p.0 == kind && v.is_some())
            .max_by(|a, b| analytic(&g, a.0).abs().total_cmp(&analytic(&g, b.0).abs()))
        else {
            panic!("no {kind:?} parameter");
        };
        let a = analytic(&g, p) as f32;
        for wrong in [a * 1.01, -a] {
            let mut bad = g.clone();
            set_analytic(&mut bad, p, wrong);
            assert!(
                !compare(&bad, &fd).failures.is_empty(),
                "{kind:?}: planted {a} -> {wrong} not caught"
            );
        }
    }
}

/// ⟨ȳ, J v⟩ = ⟨Jᵀ ȳ, v⟩ for random directions v over every parameter at once, J v by central
/// differences of the reference along v.
#[test]
fn dot_product_identity() {
    let case = random_case(3, 24);
    let g = backward(&case);
    let ps = params(&case);
    let base = refs(&case);
    let mut rng = SplitMix(99);
    for trial in 0..4 {
        let v: Vec<f64> = ps.iter().map(|_| rng.range(-1.0, 1.0) as f64).collect();
        let along = |h: f64| {
            let mut r = base.clone();
            for (&p, &vi) in ps.iter().zip(&v) {
                nudge(&mut r, p, h * vi);
            }
            loss(&case, &r)
        };
        let jv = (along(H) - along(-H)) / (2.0 * H);
        let jtv: f64 = ps.iter().zip(&v).map(|(&p, vi)| analytic(&g, p) * vi).sum();
        let scale: f64 = ps
            .iter()
            .zip(&v)
            .map(|(&p, vi)| (analytic(&g, p) * vi).abs())
            .sum();
        println!("trial {trial}: <y, Jv> = {jv:e}, <J^T y, v> = {jtv:e}");
        assert!(
            (jv - jtv).abs() <= 1e-3 * scale,
            "trial {trial}: {jv} vs {jtv} (scale {scale})"
        );
    }
}

/// A single-component case with the given surfels and rays, identity-placed, random ȳ.
fn small_case(s: Surfels, rays: Vec<TraceRay>, placement: Rigid) -> Case {
    let mut rng = SplitMix(7);
    let grads = rays.iter().map(|_| random_grad(&mut rng)).collect();
    Case {
        components: vec![s],
        transforms: vec![placement],
        rays,
        grads,
    }
}

fn tilt(axis: Vec3, angle: f32) -> [f32; 4] {
    glam::Quat::from_axis_angle(axis.normalize(), angle).to_array()
}

#[test]
fn grazing_hits() {
    // Surfels whose plane the rays meet at 3° to 6°: t, ξ and their derivatives carry 1/(d·n).
    let mut s = Surfels::with_sh_degree(0);
    push(
        &mut s,
        [0.0, 0.0, 0.0],
        tilt(Vec3::Y, 0.02),
        [0.6, 0.4],
        0.8,
        0.3,
    );
    push(
        &mut s,
        [0.5, 0.05, -0.02],
        tilt(Vec3::X, 0.03),
        [0.5, 0.5],
        0.6,
        0.7,
    );
    push(
        &mut s,
        [1.5, 0.0, 0.0],
        tilt(Vec3::Y, 1.4),
        [0.3, 0.3],
        0.7,
        0.5,
    );
    let rays = (0..6)
        .map(|k| {
            let dz = -0.05 - 0.01 * k as f32;
            ray(
                Vec3::new(-1.5, 0.02 * k as f32, 0.08),
                Vec3::new(1.0, 0.0, dz),
            )
        })
        .collect();
    let case = small_case(s, rays, Rigid::IDENTITY);
    assert!(forward(&case).iter().all(|r| r.hits >= 2));
    assert_matches("grazing", &backward(&case), &differences(&case, &all));
}

#[test]
fn coplanar_overlapping_surfels() {
    // Two discs in the plane z = 0, every ray meets both at the same t: the tie goes to the
    // lower index, in the fast path and the reference alike.
    let mut s = Surfels::with_sh_degree(0);
    push(
        &mut s,
        [0.05, 0.02, 0.0],
        [0.0, 0.0, 0.0, 1.0],
        [0.3, 0.2],
        0.7,
        0.2,
    );
    push(
        &mut s,
        [0.0, 0.0, 0.0],
        tilt(Vec3::Z, 0.7),
        [0.25, 0.3],
        0.5,
        0.9,
    );
    push(
        &mut s,
        [0.0, 0.1, -0.5],
        tilt(Vec3::X, 0.4),
        [0.4, 0.4],
        0.6,
        0.5,
    );
    let rays: Vec<TraceRay> = (0..5)
        .map(|k| {
            ray(
                Vec3::new(0.03 * k as f32, -0.02, 2.0),
                Vec3::new(0.01, 0.02, -1.0),
            )
        })
        .collect();
    let case = small_case(s, rays, Rigid::IDENTITY);
    let base = refs(&case);
    for (r, fast) in case.rays.iter().zip(forward(&case)) {
        let slow = composite_ref(
            &base,
            r.origin.map(f64::from),
            r.dir.map(f64::from),
            0.0,
            f64::INFINITY,
        );
        assert_eq!(fast.hits, slow.hits);
        assert!((fast.base_color[0] as f64 - slow.base_color[0]).abs() < 1e-5);
    }
    // In-plane parameters only (see the module doc): the tied surfels 0 and 1 keep their order.
    let in_plane = |p: Param| match p.0 {
        Kind::Position => p.2 == 2 || p.3 != 2,
        Kind::Rotation => p.2 == 2,
        Kind::Translation | Kind::Omega => false,
        _ => true,
    };
    assert_matches("coplanar", &backward(&case), &differences(&case, &in_plane));
}

#[test]
fn capped_surfel_has_no_opacity_gradient() {
    // Opacity 0.999 hit near its centre: α = 0.99 whatever the opacity, so dL/dopacity = 0 and
    // the geometry reaches L through t, x and n only.
    let mut s = Surfels::with_sh_degree(0);
    push(
        &mut s,
        [0.0, 0.0, 0.0],
        tilt(Vec3::X, 0.3),
        [0.5, 0.5],
        0.999,
        0.4,
    );
    push(
        &mut s,
        [0.0, 0.0, -0.4],
        tilt(Vec3::Y, 0.2),
        [0.5, 0.5],
        0.5,
        0.8,
    );
    let rays = vec![
        ray(Vec3::new(0.0, 0.0, 2.0), Vec3::new(0.001, 0.002, -1.0)),
        ray(Vec3::new(0.02, 0.0, 2.0), Vec3::new(0.0, 0.0, -1.0)),
    ];
    let case = small_case(s, rays, random_placement());
    let g = backward(&case);
    assert_eq!(g.surfels[0].opacity[0], 0.0);
    assert!(g.surfels[0].position[0].iter().any(|&x| x != 0.0));
    assert_matches("capped", &g, &differences(&case, &all));
}

fn random_placement() -> Rigid {
    Rigid {
        rotation: tilt(Vec3::new(0.3, 1.0, 0.2), 0.05),
        translation: [0.01, -0.02, 0.03],
    }
}

#[test]
fn hit_near_the_support_edge() {
    // |ξ| = 2.99, just inside CUTOFF = 3: α = 0.9·exp(−½·2.99²) ≈ 0.011 > MIN_ALPHA.
    let mut s = Surfels::with_sh_degree(0);
    push(
        &mut s,
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
        [0.1, 0.2],
        0.9,
        0.4,
    );
    push(
        &mut s,
        [0.3, 0.0, -0.3],
        tilt(Vec3::Y, 0.1),
        [0.4, 0.4],
        0.5,
        0.8,
    );
    let x = 0.299f32;
    assert!(x / 0.1 < CUTOFF);
    let rays = vec![ray(Vec3::new(x, 0.0, 2.0), Vec3::new(0.0, 0.0, -1.0))];
    let case = small_case(s, rays, Rigid::IDENTITY);
    assert_eq!(forward(&case)[0].hits, 2);
    let g = backward(&case);
    assert!(g.surfels[0].opacity[0] != 0.0);
    assert_matches("support edge", &g, &differences(&case, &all));
}

/// The chain rules from the means to the sums, against f32 central differences.
#[test]
fn mean_chain_rules_match_finite_differences() {
    let mut rng = SplitMix(5);
    let fields = |r: &SurfaceRecord| {
        let (p, n, a) = (r.position, r.normal, r.base_color);
        [
            r.depth,
            p[0],
            p[1],
            p[2],
            n[0],
            n[1],
            n[2],
            a[0],
            a[1],
            a[2],
            r.metallic,
            r.roughness,
            r.alpha,
        ]
    };
    let set = |r: &mut SurfaceRecord, k: usize, v: f32| match k {
        0 => r.depth = v,
        1..=3 => r.position[k - 1] = v,
        4..=6 => r.normal[k - 4] = v,
        7..=9 => r.base_color[k - 7] = v,
        10 => r.metallic = v,
        11 => r.roughness = v,
        _ => r.alpha = v,
    };
    for _ in 0..10 {
        let mut rec = SurfaceRecord::default();
        for k in 0..13 {
            set(&mut rec, k, rng.range(0.2, 1.0));
        }
        let gd = rng.range(-1.0, 1.0);
        let g3 = [0; 3].map(|_| rng.range(-1.0, 1.0));
        let (gm, gr) = (rng.range(-1.0, 1.0), rng.range(-1.0, 1.0));
        let dot3 = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        type Loss<'a> = Box<dyn Fn(&SurfaceRecord) -> f32 + 'a>;
        let checks: Vec<(&str, Loss, RecordGrad)> = vec![
            (
                "depth",
                Box::new(|r: &SurfaceRecord| gd * r.mean_depth()),
                rec.mean_depth_grad(gd),
            ),
            (
                "position",
                Box::new(|r: &SurfaceRecord| dot3(g3, r.mean_position())),
                rec.mean_position_grad(g3),
            ),
            (
                "normal",
                Box::new(|r: &SurfaceRecord| dot3(g3, r.unit_normal())),
                rec.unit_normal_grad(g3),
            ),
            (
                "material",
                Box::new(|r: &SurfaceRecord| {
                    dot3(g3, r.mean_base_color()) + gm * r.mean_metallic() + gr * r.mean_roughness()
                }),
                rec.mean_material_grad(g3, gm, gr),
            ),
        ];
        for (name, l, g) in checks {
            let analytic = grad_vec(&g);
            let h = 1e-3f32;
            for (k, (&a, x)) in analytic.iter().zip(fields(&rec)).enumerate() {
                let (mut p, mut m) = (rec, rec);
                set(&mut p, k, x + h);
                set(&mut m, k, x - h);
                let fd = ((l(&p) - l(&m)) / (2.0 * h)) as f64;
                assert!(
                    (a - fd).abs() <= 2e-3 * (1.0 + fd.abs()),
                    "{name}, field {k}: {a} vs fd {fd}"
                );
            }
        }
    }
    // Nothing hit: every mean is the constant 0.
    let empty = SurfaceRecord::default();
    assert!(empty.mean_depth_grad(1.0).is_zero());
    assert!(empty.unit_normal_grad([1.0; 3]).is_zero());
    assert!(empty.mean_position_grad([1.0; 3]).is_zero());
    assert!(empty.mean_material_grad([1.0; 3], 1.0, 1.0).is_zero());
}

#[test]
fn deterministic_across_thread_counts() {
    let case = random_case(4, 5 * RAY_CHUNK + 17);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("a rayon pool")
            .install(|| backward(&case))
    };
    let one = run(1);
    let two = run(2);
    assert!(one
        .surfels
        .iter()
        .any(|s| s.opacity.iter().any(|&x| x != 0.0)));
    assert_eq!(one, two, "the gradients depend on the thread count");
    assert_eq!(one, run(3));
}

/// Stage 3's fixed-geometry path: `composite_hits` returns `composite`'s record and the hits its
/// material sums are made of, so `set_materials` rebuilds those sums for other materials
/// exactly (same weights, same order of additions: compared bit for bit), and the
/// materials-only adjoint (`material_backward`, `scatter_material_grad`) equals the material
/// part of `composite_backward`. The same w_j, but there recovered back to front by dividing the
/// transmittance by (1 − α) with α up to 0.99, which amplifies f32 round-off up to 100× per hit
/// (measured worst 9e-5 relative on this case); the forward's products are the exact ones. So
/// 5e-4 relative is allowed, plus 1e-6 of the largest gradient for the near-zero ones.
#[test]
fn materials_only_path_matches_the_full_composite() {
    use lightfuse::trace::{scatter_material_grad, MaterialGrads, WeightedHit};
    let mut case = random_case(6, 3 * RAY_CHUNK + 5);
    let parts: Vec<&Surfels> = case.components.iter().collect();
    let mut scene = TraceScene::from_components(&parts);
    let mut hits_of = Vec::new();
    let mut kept = Vec::new();
    {
        let placed = scene.place(&case.transforms);
        for r in &case.rays {
            let mut hits: Vec<WeightedHit> = Vec::new();
            let rec = placed.composite_hits(r.origin, r.dir, r.t_min, r.t_max, &mut hits);
            assert_eq!(rec, placed.composite(r.origin, r.dir, r.t_min, r.t_max));
            assert_eq!(rec.hits as usize, hits.len());
            kept.push(rec);
            hits_of.push(hits);
        }
    }
    assert!(hits_of.iter().map(Vec::len).sum::<usize>() > case.rays.len());
    // Other materials: the kept hits rebuild what a fresh composite returns.
    let mut rng = SplitMix(7);
    for s in &mut case.components {
        for i in 0..s.len() {
            s.base_color[i] = [rng.f32(), rng.f32(), rng.f32()];
            s.metallic[i] = rng.f32();
            s.roughness[i] = rng.f32();
        }
    }
    let parts: Vec<&Surfels> = case.components.iter().collect();
    scene.set_materials(&parts);
    let placed = scene.place(&case.transforms);
    for ((r, rec), hits) in case.rays.iter().zip(&kept).zip(&hits_of) {
        let mut again = *rec;
        again.set_materials(hits, &parts);
        assert_eq!(again, placed.composite(r.origin, r.dir, r.t_min, r.t_max));
    }
    // The materials-only adjoint, both ways, against the full backward's material part.
    let full = placed.composite_backward(&parts, &case.rays, &case.grads, false);
    let zeros = || -> Vec<MaterialGrads> {
        parts
            .iter()
            .map(|s| MaterialGrads::zeros(s.len()))
            .collect()
    };
    let mut traced = zeros();
    placed.material_backward(&case.rays, &case.grads, &mut traced);
    let mut kept_hits = zeros();
    for (hits, g) in hits_of.iter().zip(&case.grads) {
        scatter_material_grad(hits, g, &mut kept_hits);
    }
    assert_eq!(traced, kept_hits, "same hits, same order, same sums");
    let largest = full
        .surfels
        .iter()
        .flat_map(|f| {
            f.base_color
                .iter()
                .flatten()
                .chain(&f.metallic)
                .chain(&f.roughness)
        })
        .fold(0.0f32, |a, &b| a.max(b.abs()));
    for (f, m) in full.surfels.iter().zip(&traced) {
        for i in 0..f.metallic.len() {
            let pairs = (0..3)
                .map(|k| (f.base_color[i][k], m.base_color[i][k]))
                .chain([
                    (f.metallic[i], m.metallic[i]),
                    (f.roughness[i], m.roughness[i]),
                ]);
            for (a, b) in pairs {
                assert!(
                    (a - b).abs() <= 5e-4 * a.abs() + 1e-6 * largest,
                    "material gradient {b} vs composite_backward's {a}"
                );
            }
        }
    }
    assert!(largest > 0.0, "the case must reach the materials");
}
