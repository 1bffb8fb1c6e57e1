//! The 2DGS splatting kernel against its f64 reference (`lightfuse::splat::reference`).
//!
//! Tolerances, and why:
//! - Forward vs reference: the fast path evaluates the same hits in f32 (ray–plane
//!   intersection via affine coefficients, then `exp`), the reference in f64. A hit's α then
//!   differs by ~1e-6 relative; after compositing tens of hits, colour, opacity and normal sums
//!   differ by ~1e-5 and depth (metres, ~1–6 here) by ~1e-5 relative (largest seen: 3.3e-5).
//!   We allow 5e-4 absolute on colour, opacity and normal and 5e-4 relative on the depths, 20×,
//!   yet a missed hit (α ≥ 1/255 ≈ 4e-3) or a wrong order still shows up. Each comparison is
//!   checked to catch a planted error of that size.
//! - Gradients vs central differences of the f64 reference: differences are taken in f64 with
//!   h = 1e-6 (truncation ~h², round-off ~1e-16·|L|/h ≈ 1e-8), so they are exact to far below
//!   the f32 backward's own error, which is relative (~1e-5 after summing many pixels with
//!   cancellation) plus absolute noise proportional to the largest gradient of the same kind.
//!   Accepted: |analytic − fd| ≤ 2e-4 |fd| + 2e-4 · max|fd| over that parameter kind, ~30× the
//!   worst error seen (6e-6 of that sum). A planted 0.5% error in the largest gradient of every
//!   kind must be caught.
//! - The forward is piecewise smooth: a hit appears or vanishes at the support edge (|ξ| = 3) and
//!   at α = 1/255, depth switches between plane and centre where the low-pass filter takes over,
//!   and the transmittance cut-off and the median switch. A difference straddling one of these is
//!   not a derivative. We detect it instead of hand-picking surfels: the difference with h and
//!   with h/2 must agree (they differ by a factor ~2 when a jump lies within h), otherwise the
//!   parameter is skipped; at most 2% may be skipped, which the test asserts (none is, today).
//! - Exactly edge-on surfels are avoided on purpose (a tilt of 0.3° or more): with n ⟂ (μ − o)
//!   the side that faces the camera, hence the sign of the rendered normal, is decided by
//!   rounding, and f32 and f64 may decide differently.

use glam::{DQuat, DVec3, Mat3, Quat, Vec3};
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::transform;
use lightfuse::scene::{sh_coeffs, Camera, Rigid, Surfels};
use lightfuse::splat::reference::{self, RefComponent, RefImage};
use lightfuse::splat::{self, ImageGrad, Placement, SplatImage};

fn look_at(eye: Vec3, target: Vec3, w: u32, h: u32, f: f32, cx: f32, cy: f32) -> Camera {
    Camera {
        fl_y: f * 1.03,
        cx,
        cy,
        ..Camera::look_at(eye.to_array(), target.to_array(), w, h, f)
    }
}

fn random_sh(rng: &mut SplitMix, degree: u8, dc: f32, rest: f32) -> Vec<[f32; 3]> {
    (0..sh_coeffs(degree))
        .map(|k| {
            let a = if k == 0 { dc } else { rest };
            [rng.range(-a, a), rng.range(-a, a), rng.range(-a, a)]
        })
        .collect()
}

fn push(s: &mut Surfels, p: Vec3, q: Quat, scale: [f32; 2], opacity: f32, sh: &[[f32; 3]]) {
    s.push(
        p.to_array(),
        q.normalize().to_array(),
        scale,
        opacity,
        sh,
        [0.5; 3],
        0.0,
        0.5,
    );
}

/// A rotation whose normal is `tilt` radians off perpendicular to `a`: the surfel is seen
/// (nearly) edge-on. Exactly edge-on (tilt 0) leaves which face is in front to rounding, so the
/// normal's sign (flipped to face the camera) would be arbitrary.
fn edge_on(a: Vec3, tilt: f32, rng: &mut SplitMix) -> Quat {
    let r = Vec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    );
    let n = a.cross(r).normalize();
    let tu = a.normalize();
    let tv = n.cross(tu);
    // Rotating about t_v tilts n towards t_u = a / |a|.
    Quat::from_mat3(&Mat3::from_cols(tu, tv, n)) * Quat::from_rotation_y(tilt)
}

/// A few hundred surfels of every awkward kind around a camera at (0, 1, 4) looking at −Z.
fn awkward_scene(seed: u64) -> (Surfels, Surfels, Rigid, Camera) {
    let mut rng = SplitMix(seed);
    let camera = look_at(
        Vec3::new(0.0, 1.0, 4.0),
        Vec3::new(0.1, 0.9, 0.0),
        70,
        50,
        55.0,
        35.3,
        24.8,
    );
    let eye = Vec3::new(0.0, 1.0, 4.0);
    let mut bg = Surfels::with_sh_degree(3);
    for k in 0..260 {
        let p = Vec3::new(
            rng.range(-2.5, 2.5),
            rng.range(-0.8, 2.8),
            // Some behind the camera (z > 4).
            rng.range(-2.0, 5.0),
        );
        let q = if k % 13 == 0 {
            edge_on(p - eye, 0.005, &mut rng)
        } else {
            Quat::from_array(rng.unit_quat())
        };
        // From sub-pixel to large; anisotropic.
        let big = k % 7 == 0;
        let s = if big { 0.3 } else { 0.06 };
        let scale = [rng.range(0.004, s), rng.range(0.004, s)];
        // Some above 0.99 so α is clamped, some faint.
        let opacity = if k % 11 == 0 {
            0.997
        } else {
            rng.range(0.02, 1.0)
        };
        let mut sh = random_sh(&mut rng, 3, 1.5, 0.4);
        if k % 5 == 0 {
            sh[0][1] = -3.0; // clamped green channel
        }
        push(&mut bg, p, q, scale, opacity, &sh);
    }
    // Large surfels straddling the near plane right in front of the camera.
    for k in 0..4 {
        let p = eye + Vec3::new(0.05 * k as f32 - 0.1, 0.02, -0.02 - 0.01 * k as f32);
        let q = Quat::from_array(rng.unit_quat());
        let sh = random_sh(&mut rng, 3, 1.0, 0.2);
        push(&mut bg, p, q, [0.15, 0.1], 0.3, &sh);
    }
    let mut obj = Surfels::with_sh_degree(3);
    for _ in 0..80 {
        let p = Vec3::new(
            rng.range(-0.6, 0.6),
            rng.range(-0.6, 0.6),
            rng.range(-0.6, 0.6),
        );
        let sh = random_sh(&mut rng, 3, 1.5, 0.4);
        let scale = [rng.range(0.01, 0.12), rng.range(0.01, 0.12)];
        push(
            &mut obj,
            p,
            Quat::from_array(rng.unit_quat()),
            scale,
            rng.range(0.1, 1.0),
            &sh,
        );
    }
    let t = Rigid {
        rotation: Quat::from_axis_angle(Vec3::new(0.3, 1.0, -0.2).normalize(), 0.8).to_array(),
        translation: [0.4, 1.1, 0.5],
    };
    (bg, obj, t, camera)
}

/// Largest error over a map, absolute (`rel = false`) or relative to max(1, |reference|).
fn max_err(fast: &[f32], reference: &[f64], rel: bool) -> f64 {
    fast.iter()
        .zip(reference)
        .map(|(a, b)| {
            let e = (*a as f64 - b).abs();
            if rel {
                e / b.abs().max(1.0)
            } else {
                e
            }
        })
        .fold(0.0, f64::max)
}

fn flat3f(v: &[[f32; 3]]) -> Vec<f32> {
    v.iter().flatten().copied().collect()
}

fn flat3d(v: &[[f64; 3]]) -> Vec<f64> {
    v.iter().flatten().copied().collect()
}

/// The five maps' errors (colour, opacity, normal absolute; depths relative).
fn image_errors(fast: &SplatImage, r: &RefImage) -> [f64; 5] {
    [
        max_err(&flat3f(&fast.color), &flat3d(&r.color), false),
        max_err(&fast.alpha, &r.alpha, false),
        max_err(&flat3f(&fast.normal), &flat3d(&r.normal), false),
        max_err(&fast.depth, &r.depth, true),
        max_err(&fast.median_depth, &r.median_depth, true),
    ]
}

/// See the module doc.
const FORWARD_TOL: f64 = 5e-4;

#[test]
fn forward_matches_reference() {
    for seed in [1u64, 2, 3] {
        let (bg, obj, t, camera) = awkward_scene(seed);
        let comps = [
            Placement::world(&bg),
            Placement {
                surfels: &obj,
                transform: t,
            },
        ];
        let fast = splat::forward(&comps, &camera).image;
        let refc: Vec<_> = comps.iter().map(RefComponent::from_placement).collect();
        let r = reference::render(&refc, &camera);
        assert_eq!(fast.pixels(), r.alpha.len());

        let errs = image_errors(&fast, &r);
        eprintln!("seed {seed}: colour, alpha, normal, depth, median errors {errs:?}");
        for (name, e) in ["colour", "alpha", "normal", "depth", "median depth"]
            .iter()
            .zip(errs)
        {
            assert!(e <= FORWARD_TOL, "seed {seed}: {name} differs by {e}");
        }
        // The scene is not trivial: many pixels covered, some fully, some with nothing.
        let covered = r.alpha.iter().filter(|a| **a > 0.01).count();
        let opaque = r.alpha.iter().filter(|a| **a > 0.9).count();
        assert!(covered > fast.pixels() / 3, "only {covered} pixels covered");
        assert!(opaque > 50, "only {opaque} opaque pixels");
        let thin = r.alpha.iter().filter(|a| **a < 0.5).count();
        assert!(thin > 50, "only {thin} thin pixels");

        // The comparison catches one planted error of the tolerance's size in any map.
        let mut planted = fast.clone();
        let k = planted.pixels() / 2 + 7;
        planted.color[k][1] += 2.0 * FORWARD_TOL as f32;
        planted.depth[k + 3] += 2.0 * FORWARD_TOL as f32 * planted.depth[k + 3].abs().max(1.0);
        planted.normal[k + 5][2] -= 2.0 * FORWARD_TOL as f32;
        let e = image_errors(&planted, &r);
        assert!(e[0] > FORWARD_TOL && e[2] > FORWARD_TOL && e[3] > FORWARD_TOL);
    }
}

/// Rendering one component placed by a transform equals rendering its surfels moved into the
/// world by hand (eq. state-assembly).
#[test]
fn placement_equals_moved_surfels() {
    let (_, obj, t, camera) = awkward_scene(9);
    let mut moved = obj.clone();
    for i in 0..moved.len() {
        moved.position[i] = t.transform_point(obj.position[i]);
        moved.rotation[i] = t.transform_rotation(obj.rotation[i]);
    }
    let a = splat::forward(
        &[Placement {
            surfels: &obj,
            transform: t,
        }],
        &camera,
    )
    .image;
    let b = splat::render(&moved, &camera);
    let d = max_err(
        &a.alpha,
        &b.alpha.iter().map(|x| *x as f64).collect::<Vec<_>>(),
        false,
    );
    assert!(d < 1e-5, "alpha differs by {d}");
    assert!(b.alpha.iter().any(|x| *x > 0.5));
}

// ---------------------------------------------------------------------------------------------
// Gradients.

/// A small scene for finite differences: a background of 12 surfels and an object of 6 placed by
/// a non-trivial transform, 24×24 pixels. Some surfels are sub-pixel (the low-pass filter
/// decides their hits), one is nearly edge-on, one has opacity above 0.99 (clamped α), one has
/// a clamped colour channel, and all carry degree-3 SH.
fn gradient_scene() -> (Surfels, Surfels, Rigid, Camera) {
    let mut rng = SplitMix(77);
    let eye = Vec3::new(0.0, 0.0, 3.0);
    let camera = look_at(eye, Vec3::new(0.02, -0.03, 0.0), 24, 24, 26.0, 12.2, 11.9);
    let mut bg = Surfels::with_sh_degree(3);
    for k in 0..12 {
        let p = Vec3::new(
            rng.range(-0.8, 0.8),
            rng.range(-0.8, 0.8),
            rng.range(-1.0, 0.8),
        );
        let q = if k == 3 {
            // Nearly edge-on: 1.5° off.
            edge_on(p - eye, 0.026, &mut rng)
        } else {
            Quat::from_array(rng.unit_quat())
        };
        let scale = if k % 4 == 1 {
            [rng.range(0.005, 0.02), rng.range(0.005, 0.02)]
        } else {
            [rng.range(0.08, 0.35), rng.range(0.08, 0.35)]
        };
        let opacity = if k == 5 { 0.996 } else { rng.range(0.3, 0.85) };
        let mut sh = random_sh(&mut rng, 3, 1.0, 0.3);
        if k == 7 {
            sh[0][2] = -4.0;
        }
        push(&mut bg, p, q, scale, opacity, &sh);
    }
    let mut obj = Surfels::with_sh_degree(3);
    for _ in 0..6 {
        let p = Vec3::new(
            rng.range(-0.3, 0.3),
            rng.range(-0.3, 0.3),
            rng.range(-0.3, 0.3),
        );
        let scale = [rng.range(0.08, 0.25), rng.range(0.08, 0.25)];
        let sh = random_sh(&mut rng, 3, 1.0, 0.3);
        push(
            &mut obj,
            p,
            Quat::from_array(rng.unit_quat()),
            scale,
            rng.range(0.3, 0.85),
            &sh,
        );
    }
    let t = Rigid {
        rotation: Quat::from_axis_angle(Vec3::new(-0.5, 0.7, 0.2).normalize(), 0.6).to_array(),
        translation: [0.15, -0.1, 0.6],
    };
    (bg, obj, t, camera)
}

/// Random weights on every output channel: the loss is L = Σ weight · output.
fn random_weights(w: u32, h: u32, seed: u64) -> ImageGrad {
    let mut rng = SplitMix(seed);
    let mut g = ImageGrad::zeros(w, h);
    let mut r = || rng.range(-1.0, 1.0);
    for i in 0..g.pixels() {
        g.color[i] = [r(), r(), r()];
        g.alpha[i] = r();
        g.depth[i] = r();
        g.median_depth[i] = r();
        g.normal[i] = [r(), r(), r()];
    }
    g
}

fn loss(r: &RefImage, g: &ImageGrad) -> f64 {
    let mut l = 0.0;
    for i in 0..g.pixels() {
        for c in 0..3 {
            l += g.color[i][c] as f64 * r.color[i][c] + g.normal[i][c] as f64 * r.normal[i][c];
        }
        l += g.alpha[i] as f64 * r.alpha[i]
            + g.depth[i] as f64 * r.depth[i]
            + g.median_depth[i] as f64 * r.median_depth[i];
    }
    l
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Position,
    Rotation,
    Scale,
    Opacity,
    Sh,
    Translation,
    Omega,
}

/// Adds `h` to one parameter: (kind, component, surfel, coordinate).
fn nudge(comps: &mut [RefComponent], kind: Kind, c: usize, i: usize, k: usize, h: f64) {
    let s = &mut comps[c];
    match kind {
        Kind::Position => s.surfels[i].position[k] += h,
        Kind::Rotation => s.surfels[i].rotation[k] += h,
        Kind::Scale => s.surfels[i].scale[k] += h,
        Kind::Opacity => s.surfels[i].opacity += h,
        Kind::Sh => s.surfels[i].sh[k / 3][k % 3] += h,
        Kind::Translation => s.translation[k] += h,
        Kind::Omega => {
            let mut axis = DVec3::ZERO;
            axis[k] = h;
            let q = DQuat::from_array(s.rotation);
            s.rotation = (DQuat::from_scaled_axis(axis) * q).to_array();
        }
    }
}

/// |analytic − fd| ≤ 2e-4 |fd| + 2e-4 · scale (module doc).
fn close(analytic: f64, fd: f64, scale: f64) -> bool {
    (analytic - fd).abs() <= 2e-4 * fd.abs() + 2e-4 * scale
}

#[test]
fn gradients_match_finite_differences() {
    let (bg, obj, t, camera) = gradient_scene();
    check_gradients(&bg, &obj, t, &camera);
}

/// Compares every gradient of the scene with central differences of the f64 reference.
fn check_gradients(bg: &Surfels, obj: &Surfels, t: Rigid, camera: &Camera) {
    let camera = *camera;
    let comps = [
        Placement::world(bg),
        Placement {
            surfels: obj,
            transform: t,
        },
    ];
    let weights = random_weights(camera.w, camera.h, 5);
    let fwd = splat::forward(&comps, &camera);
    let grads = fwd.backward(&weights);
    let base: Vec<RefComponent> = comps.iter().map(RefComponent::from_placement).collect();
    let covered = reference::render(&base, &camera)
        .alpha
        .iter()
        .filter(|a| **a > 0.05)
        .count();
    assert!(covered > 200, "the scene covers only {covered} pixels");

    let fd = |kind, c, i, k, h: f64| {
        let mut plus = base.clone();
        nudge(&mut plus, kind, c, i, k, h);
        let mut minus = base.clone();
        nudge(&mut minus, kind, c, i, k, -h);
        (loss(&reference::render(&plus, &camera), &weights)
            - loss(&reference::render(&minus, &camera), &weights))
            / (2.0 * h)
    };

    // (kind, component, surfel, coordinate, analytic)
    let mut params: Vec<(Kind, usize, usize, usize, f64)> = Vec::new();
    for (c, g) in grads.surfels.iter().enumerate() {
        let n = comps[c].surfels.len();
        let stride = comps[c].surfels.sh_stride();
        for i in 0..n {
            for k in 0..3 {
                params.push((Kind::Position, c, i, k, g.position[i][k] as f64));
            }
            for k in 0..4 {
                params.push((Kind::Rotation, c, i, k, g.rotation[i][k] as f64));
            }
            for k in 0..2 {
                params.push((Kind::Scale, c, i, k, g.scale[i][k] as f64));
            }
            params.push((Kind::Opacity, c, i, 0, g.opacity[i] as f64));
            for k in 0..3 * stride {
                params.push((Kind::Sh, c, i, k, g.sh[i * stride + k / 3][k % 3] as f64));
            }
        }
        for k in 0..3 {
            params.push((
                Kind::Translation,
                c,
                0,
                k,
                grads.transforms[c].translation[k] as f64,
            ));
            params.push((Kind::Omega, c, 0, k, grads.transforms[c].rotation[k] as f64));
        }
    }

    const H: f64 = 1e-6;
    let mut results = Vec::new(); // (kind, analytic, fd, label)
    let mut skipped = 0;
    for &(kind, c, i, k, analytic) in &params {
        let d1 = fd(kind, c, i, k, H);
        let d2 = fd(kind, c, i, k, H / 2.0);
        // A jump within h makes the two differ by ~2×; smooth ones agree to ~1e-9.
        if (d1 - d2).abs() > 1e-6 + 1e-4 * d1.abs() {
            skipped += 1;
            eprintln!(
                "skipped {kind:?} c{c} s{i} k{k}: fd {d1} vs {d2} (a discontinuity within h)"
            );
            continue;
        }
        results.push((kind, analytic, d2, format!("{kind:?} c{c} s{i} k{k}")));
    }
    assert!(
        skipped * 50 <= params.len(),
        "{skipped} of {} parameters straddle a discontinuity",
        params.len()
    );

    let kinds = [
        Kind::Position,
        Kind::Rotation,
        Kind::Scale,
        Kind::Opacity,
        Kind::Sh,
        Kind::Translation,
        Kind::Omega,
    ];
    let mut failures = Vec::new();
    for kind in kinds {
        let of_kind: Vec<_> = results.iter().filter(|r| r.0 == kind).collect();
        let scale = of_kind.iter().map(|r| r.2.abs()).fold(0.0, f64::max);
        // Not vacuous: every kind has real gradients here.
        assert!(scale > 1e-2, "{kind:?}: largest gradient only {scale}");
        let mut worst = 0.0f64;
        for (_, a, d, label) in &of_kind {
            worst = worst.max((a - d).abs() / (d.abs() + scale));
            if !close(*a, *d, scale) {
                failures.push(format!("{label}: analytic {a}, finite difference {d}"));
            }
        }
        eprintln!(
            "{kind:?}: {} checked, largest |fd| {scale:.3e}, worst error {worst:.2e} of (|fd| + max)",
            of_kind.len()
        );
        // A 0.5% error in the largest gradient of this kind would be caught.
        let top = of_kind
            .iter()
            .max_by(|x, y| x.2.abs().total_cmp(&y.2.abs()))
            .expect("one gradient");
        assert!(
            !close(top.2 * 1.005, top.2, scale),
            "{kind:?}: a 0.5% error would pass"
        );
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Backward is linear in the upstream gradient and deterministic: running it twice gives the
/// same bits, and doubling the weights doubles every gradient.
#[test]
fn backward_is_deterministic_and_linear() {
    let (bg, obj, t, camera) = awkward_scene(4);
    let comps = [
        Placement::world(&bg),
        Placement {
            surfels: &obj,
            transform: t,
        },
    ];
    let fwd = splat::forward(&comps, &camera);
    let w = random_weights(camera.w, camera.h, 8);
    let a = fwd.backward(&w);
    assert_eq!(a, fwd.backward(&w));
    let mut w2 = w.clone();
    for i in 0..w2.pixels() {
        w2.color[i] = w2.color[i].map(|x| 2.0 * x);
        w2.normal[i] = w2.normal[i].map(|x| 2.0 * x);
        w2.alpha[i] *= 2.0;
        w2.depth[i] *= 2.0;
        w2.median_depth[i] *= 2.0;
    }
    let b = fwd.backward(&w2);
    for (ga, gb) in a.surfels.iter().zip(&b.surfels) {
        for (x, y) in ga
            .position
            .iter()
            .flatten()
            .zip(gb.position.iter().flatten())
        {
            assert!((2.0 * x - y).abs() <= 1e-5 * y.abs().max(1.0), "{x} {y}");
        }
    }
    assert!(a.surfels[0].position.iter().flatten().any(|x| *x != 0.0));
}

// ---------------------------------------------------------------------------------------------
// Edge cases: nothing to draw, nowhere to draw, poison.

fn assert_empty(img: &SplatImage) {
    assert!(img.alpha.iter().all(|a| *a == 0.0));
    assert!(img.depth.iter().all(|a| *a == 0.0));
    assert!(img.color.iter().flatten().all(|a| *a == 0.0));
    assert!(img.normal.iter().flatten().all(|a| *a == 0.0));
}

#[test]
fn empty_scene_renders_nothing() {
    let camera = look_at(
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::ZERO,
        40,
        30,
        30.0,
        20.0,
        15.0,
    );
    let empty = Surfels::with_sh_degree(3);
    let f = splat::forward(&[Placement::world(&empty)], &camera);
    assert_eq!(f.image.pixels(), 40 * 30);
    assert_empty(&f.image);
    let g = f.backward(&random_weights(40, 30, 1));
    assert_eq!(g.surfels.len(), 1);
    assert!(g.surfels[0].position.is_empty());
    assert_eq!(g.transforms[0], Default::default());
    // No components at all.
    let f = splat::forward(&[], &camera);
    assert_empty(&f.image);
    assert!(f.backward(&random_weights(40, 30, 1)).surfels.is_empty());
}

#[test]
fn surfels_behind_the_camera_are_invisible() {
    let camera = look_at(
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::ZERO,
        40,
        30,
        30.0,
        20.0,
        15.0,
    );
    let mut rng = SplitMix(3);
    let mut s = Surfels::with_sh_degree(1);
    for _ in 0..200 {
        // z > 3 + NEAR: all behind (or too near) the camera, some large enough to reach in front.
        let p = Vec3::new(
            rng.range(-2.0, 2.0),
            rng.range(-2.0, 2.0),
            rng.range(3.0 + 0.011, 6.0),
        );
        let sh = random_sh(&mut rng, 1, 1.0, 0.3);
        push(
            &mut s,
            p,
            Quat::from_array(rng.unit_quat()),
            [0.5, 0.5],
            0.9,
            &sh,
        );
    }
    let f = splat::forward(&[Placement::world(&s)], &camera);
    assert_empty(&f.image);
    let r = reference::render(
        &[RefComponent::from_placement(&Placement::world(&s))],
        &camera,
    );
    assert!(r.alpha.iter().all(|a| *a == 0.0));
    let g = f.backward(&random_weights(40, 30, 2));
    assert!(g.surfels[0].position.iter().flatten().all(|x| *x == 0.0));
    // The same surfels mirrored in front of the camera are visible: the test could fail.
    for p in s.position.iter_mut() {
        p[2] = 6.0 - p[2];
    }
    assert!(splat::render(&s, &camera).alpha.iter().any(|a| *a > 0.1));
}

#[test]
fn zero_size_images() {
    let (bg, obj, t, camera) = awkward_scene(5);
    let comps = [
        Placement::world(&bg),
        Placement {
            surfels: &obj,
            transform: t,
        },
    ];
    for (w, h) in [(0, 0), (0, 7), (9, 0)] {
        let cam = Camera { w, h, ..camera };
        let f = splat::forward(&comps, &cam);
        assert_eq!(f.image.pixels(), 0);
        assert!(f.image.color.is_empty() && f.image.alpha.is_empty());
        let g = f.backward(&ImageGrad::zeros(w, h));
        assert_eq!(g.surfels[0].position.len(), bg.len());
        assert!(g.surfels[1].sh.iter().flatten().all(|x| *x == 0.0));
    }
}

/// Poison values (NaN, ∞, zero scale, zero quaternion, opacity 0) next to good surfels: no
/// panic, finite output, and the good surfels render as if the poison were absent.
#[test]
fn poison_surfels_are_culled() {
    let camera = look_at(
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::ZERO,
        40,
        30,
        30.0,
        20.0,
        15.0,
    );
    let mut rng = SplitMix(11);
    let mut good = Surfels::with_sh_degree(0);
    for _ in 0..30 {
        let p = Vec3::new(
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        );
        push(
            &mut good,
            p,
            Quat::from_array(rng.unit_quat()),
            [0.2, 0.1],
            0.7,
            &[[1.0, 0.2, -0.3]],
        );
    }
    let mut bad = good.clone();
    let poison = [
        (
            Vec3::new(f32::NAN, 0.0, 0.0),
            Quat::IDENTITY,
            [0.2, 0.2],
            0.5,
        ),
        (
            Vec3::new(0.0, f32::INFINITY, 0.0),
            Quat::IDENTITY,
            [0.2, 0.2],
            0.5,
        ),
        (Vec3::ZERO, Quat::IDENTITY, [0.0, 0.2], 0.5),
        (Vec3::ZERO, Quat::IDENTITY, [f32::INFINITY, 0.2], 0.5),
        (Vec3::ZERO, Quat::IDENTITY, [0.2, 0.2], f32::NAN),
        (Vec3::ZERO, Quat::IDENTITY, [0.2, 0.2], 0.0),
        (Vec3::new(0.0, 0.0, 3.0), Quat::IDENTITY, [0.2, 0.2], 0.5),
    ];
    for (p, q, s, o) in poison {
        bad.push(
            p.to_array(),
            q.to_array(),
            s,
            o,
            &[[1.0; 3]],
            [0.5; 3],
            0.0,
            0.5,
        );
    }
    bad.push(
        [0.0; 3],
        [0.0; 4],
        [0.2, 0.2],
        0.5,
        &[[1.0; 3]],
        [0.5; 3],
        0.0,
        0.5,
    );
    let a = splat::render(&good, &camera);
    let f = splat::forward(&[Placement::world(&bad)], &camera);
    assert_eq!(a, f.image);
    assert!(a.alpha.iter().any(|x| *x > 0.5));
    let g = f.backward(&random_weights(40, 30, 3));
    let s = &g.surfels[0];
    assert!(s.position.iter().flatten().all(|x| x.is_finite()));
    assert!(s.rotation.iter().flatten().all(|x| x.is_finite()));
    assert!(s.sh.iter().flatten().all(|x| x.is_finite()));
}

/// The pivoted pose increment ([`transform::perturb_about`]) and its gradient
/// ([`transform::TransformGrad::about`]) agree with each other. The loss L(T) = Σᵢ aᵢ·(T xᵢ) is
/// linear in the placed points, so its gradient in [`transform::perturb`]'s parametrisation is
/// known in closed form (dL/dδ = Σ aᵢ, dL/dω = Σ (R xᵢ) × aᵢ: what the backward pass returns,
/// tested against the reference above); converted to the pivot, it must match central
/// differences of L(perturb_about(T, δ, ω, p)) at 0 with h = 1e-3 (the increment is applied
/// in f32: round-off ~1e-7·|L|/h ≈ 1e-4·|L|, truncation ~h² ≈ 1e-6), to 2e-3 (1 + |fd|), where a
/// missing (t − p) × dL/dδ term is off by O(1). A rotation step about the pivot leaves the
/// pivot where it is.
#[test]
fn pivoted_pose_increment_matches_its_gradient() {
    let mut rng = SplitMix(77);
    for _ in 0..5 {
        let mut v = || {
            Vec3::new(
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            )
        };
        let t = Rigid {
            rotation: Quat::from_scaled_axis(v()).normalize().to_array(),
            translation: (2.0 * v()).to_array(),
        };
        let pivot = (Vec3::from_array(t.translation) + 0.5 * v()).to_array();
        let xs: Vec<Vec3> = (0..6).map(|_| 0.3 * v()).collect();
        let a: Vec<Vec3> = (0..6).map(|_| v()).collect();
        let loss = |r: &Rigid| -> f64 {
            let q = DQuat::from_array(r.rotation.map(|x| x as f64)).normalize();
            let tt = DVec3::from_array(r.translation.map(|x| x as f64));
            xs.iter()
                .zip(&a)
                .map(|(x, a)| (q * x.as_dvec3() + tt).dot(a.as_dvec3()))
                .sum()
        };
        let g = transform::TransformGrad {
            translation: a.iter().copied().sum::<Vec3>().to_array(),
            rotation: xs
                .iter()
                .zip(&a)
                .map(|(x, a)| (t.quat() * *x).cross(*a))
                .sum::<Vec3>()
                .to_array(),
        }
        .about(&t, pivot);
        let h = 1e-3f32;
        for k in 0..6 {
            let step = |s: f32| {
                let mut d = [0.0f32; 6];
                d[k] = s;
                transform::perturb_about(&t, [d[0], d[1], d[2]], [d[3], d[4], d[5]], pivot)
            };
            let fd = (loss(&step(h)) - loss(&step(-h))) / (2.0 * h as f64);
            let analytic = if k < 3 {
                g.translation[k]
            } else {
                g.rotation[k - 3]
            } as f64;
            assert!(
                (fd - analytic).abs() <= 2e-3 * (1.0 + fd.abs()),
                "parameter {k}: analytic {analytic}, central difference {fd}"
            );
        }
        let turned = transform::perturb_about(&t, [0.0; 3], [0.3, -0.2, 0.1], pivot);
        let before = Vec3::from_array(pivot);
        let placed = |r: &Rigid, p: Vec3| {
            r.quat() * (t.quat().inverse() * (p - Vec3::from_array(t.translation)))
                + Vec3::from_array(r.translation)
        };
        assert!((placed(&turned, before) - before).length() < 1e-5);
    }
}
