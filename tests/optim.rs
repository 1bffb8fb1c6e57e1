//! Optimisation building blocks (`lightfuse::optim`) and metrics (`lightfuse::eval`).
//!
//! Method: every fast f32 loss is compared with a slow, obvious f64 reference written here from
//! the formula (value), and every analytic gradient with central finite differences of that f64
//! reference, one input at a time, on small random images with fixed seeds.
//!
//! Tolerances:
//! - Finite differences use h = 1e-4 on inputs of order 1 (1e-5 for depth maps around 3 m and
//!   for surfel scales around 0.05). In f64 the rounding error of a central difference is
//!   ~1e-16·|L|/h ≈ 1e-12 and the truncation error h²·|L'''|/6 is below 1e-8 for these
//!   smooth losses, so the comparison is limited by the f32 analytic gradient: we require
//!   max |analytic − FD| ≤ 1e-4 · max |FD|. Measured worst: 1.1e-6 (D-SSIM, whose moments lose
//!   digits to σ² = E[x²] − μ²), ≤ 3e-7 for the others; a wrong term is off by O(1).
//! - Kinks: L1-type losses (colour, alpha, depth, TV) get inputs whose residuals or neighbour
//!   differences are at least 0.01 ≫ h away from 0, so no difference straddles a kink and the
//!   FD is exact up to rounding; scale regularisation keeps both scale components 0.01 apart.
//! - Forward values: f32 against the f64 reference within 1e-6 relative (sums are accumulated
//!   in f64, so only per-pixel f32 rounding remains; measured worst 1.8e-7, D-SSIM). SSIM
//!   against the direct f64 reference within 1e-6 absolute (measured worst 2.2e-8).

use lightfuse::eval;
use lightfuse::optim::{self, Adam, Schedule};
use lightfuse::scene::color::srgb_encode;
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::Camera;
use std::path::Path;

// ---------- helpers ----------

fn random_image(rng: &mut SplitMix, n: usize) -> Vec<[f32; 3]> {
    (0..n).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect()
}

/// `rendered` near `target` (as during training) but every residual at least 0.01 from 0.
fn perturbed(rng: &mut SplitMix, target: &[[f32; 3]]) -> Vec<[f32; 3]> {
    target
        .iter()
        .map(|t| {
            t.map(|v| {
                let d = rng.range(0.01, 0.2);
                if rng.f32() < 0.5 {
                    v + d
                } else {
                    v - d
                }
            })
        })
        .collect()
}

fn flat3(img: &[[f32; 3]]) -> Vec<f64> {
    img.iter().flat_map(|p| p.map(|v| v as f64)).collect()
}

fn flat1(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x as f64).collect()
}

fn to3(v: &[f64]) -> Vec<[f64; 3]> {
    v.chunks(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// Central differences of `f` at `x`, one coordinate at a time.
fn finite_differences(x: &[f64], h: f64, f: impl Fn(&[f64]) -> f64) -> Vec<f64> {
    let mut x = x.to_vec();
    (0..x.len())
        .map(|i| {
            let x0 = x[i];
            x[i] = x0 + h;
            let fp = f(&x);
            x[i] = x0 - h;
            let fm = f(&x);
            x[i] = x0;
            (fp - fm) / (2.0 * h)
        })
        .collect()
}

/// max |analytic − fd| ≤ rel · max |fd|, with a message naming the worst coordinate.
fn assert_grad(name: &str, analytic: &[f64], fd: &[f64], rel: f64) {
    assert_eq!(analytic.len(), fd.len(), "{name}: gradient length");
    let scale = fd.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(
        scale > 0.0,
        "{name}: finite-difference gradient is all zero"
    );
    let (worst, err) = analytic
        .iter()
        .zip(fd)
        .map(|(a, b)| (a - b).abs())
        .enumerate()
        .fold((0, 0.0f64), |m, (i, e)| if e > m.1 { (i, e) } else { m });
    assert!(
        err <= rel * scale,
        "{name}: |analytic − FD| = {err:e} at {worst} (analytic {}, FD {}), scale {scale:e}",
        analytic[worst],
        fd[worst]
    );
}

fn assert_value(name: &str, fast: f32, reference: f64, rel: f64) {
    let err = (fast as f64 - reference).abs();
    assert!(
        err <= rel * reference.abs().max(1e-12),
        "{name}: fast {fast} vs reference {reference}"
    );
}

// ---------- slow f64 references ----------

/// SSIM straight from the definition: for every pixel and channel, weighted sums over the
/// 11×11 window with taps g(i)g(j), g ∝ exp(−d²/(2·1.5²)), outside pixels read as 0.
fn ref_ssim(a: &[[f64; 3]], b: &[[f64; 3]], w: usize, h: usize) -> f64 {
    let g: Vec<f64> = (-5i64..=5).map(|d| (-(d * d) as f64 / 4.5).exp()).collect();
    let gs: f64 = g.iter().sum();
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let mut total = 0.0;
    for c in 0..3 {
        for y in 0..h as i64 {
            for x in 0..w as i64 {
                let (mut mx, mut my, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for j in -5i64..=5 {
                    for i in -5i64..=5 {
                        let (u, v) = (x + i, y + j);
                        if u < 0 || v < 0 || u >= w as i64 || v >= h as i64 {
                            continue;
                        }
                        let k = g[(i + 5) as usize] * g[(j + 5) as usize] / (gs * gs);
                        let p = (v as usize) * w + u as usize;
                        let (s, t) = (a[p][c], b[p][c]);
                        mx += k * s;
                        my += k * t;
                        xx += k * s * s;
                        yy += k * t * t;
                        xy += k * s * t;
                    }
                }
                let (vx, vy, cov) = (xx - mx * mx, yy - my * my, xy - mx * my);
                total += (2.0 * mx * my + c1) * (2.0 * cov + c2)
                    / ((mx * mx + my * my + c1) * (vx + vy + c2));
            }
        }
    }
    total / (3 * w * h) as f64
}

fn ref_l1(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    let s: f64 = a
        .iter()
        .zip(b)
        .map(|(p, q)| (0..3).map(|c| (p[c] - q[c]).abs()).sum::<f64>())
        .sum();
    s / (3 * a.len()) as f64
}

fn ref_tv(e: &[[f64; 3]], w: usize, h: usize) -> f64 {
    let dist = |a: [f64; 3], b: [f64; 3]| (0..3).map(|c| (a[c] - b[c]).abs()).sum::<f64>();
    let (mut s, mut n) = (0.0, 0usize);
    for y in 0..h {
        for x in 0..w {
            let p = e[y * w + x];
            s += dist(e[y * w + (x + 1) % w], p);
            n += 3;
            if y + 1 < h {
                s += dist(e[(y + 1) * w + x], p);
                n += 3;
            }
        }
    }
    s / n as f64
}

fn camera(w: u32, h: u32) -> Camera {
    // A rotated, translated camera so that world and camera frames differ on every axis.
    let r = glam::Mat3::from_quat(glam::Quat::from_euler(glam::EulerRot::YXZ, 0.7, -0.4, 0.2));
    let t = [0.3f32, 1.2, -0.5];
    let mut m = [[0.0f32; 4]; 4];
    for (i, row) in m.iter_mut().enumerate().take(3) {
        for (j, v) in row.iter_mut().enumerate().take(3) {
            *v = r.col(j)[i];
        }
        row[3] = t[i];
    }
    m[3][3] = 1.0;
    Camera {
        transform_matrix: m,
        fl_x: 20.0,
        fl_y: 22.0,
        cx: 8.3,
        cy: 5.9,
        w,
        h,
    }
}

/// World points of a planar depth map through the full camera-to-world matrix, in f64.
fn ref_world_point(cam: &Camera, depth: &[f64], x: usize, y: usize) -> Option<[f64; 3]> {
    let d = depth[y * cam.w as usize + x];
    if d <= 0.0 {
        return None;
    }
    let pc = [
        d * (x as f64 + 0.5 - cam.cx as f64) / cam.fl_x as f64,
        -d * (y as f64 + 0.5 - cam.cy as f64) / cam.fl_y as f64,
        -d,
        1.0,
    ];
    let m = &cam.transform_matrix;
    Some(std::array::from_fn(|r| {
        (0..4).map(|k| m[r][k] as f64 * pc[k]).sum()
    }))
}

fn ref_depth_normal(cam: &Camera, depth: &[f64], x: usize, y: usize) -> Option<[f64; 3]> {
    let (w, h) = (cam.w as usize, cam.h as usize);
    if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
        return None;
    }
    let p = |x, y| ref_world_point(cam, depth, x, y);
    let (r, l, d, u) = (p(x + 1, y)?, p(x - 1, y)?, p(x, y + 1)?, p(x, y - 1)?);
    let dx = [r[0] - l[0], r[1] - l[1], r[2] - l[2]];
    let dy = [d[0] - u[0], d[1] - u[1], d[2] - u[2]];
    let c = [
        dy[1] * dx[2] - dy[2] * dx[1],
        dy[2] * dx[0] - dy[0] * dx[2],
        dy[0] * dx[1] - dy[1] * dx[0],
    ];
    let n = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
    Some(c.map(|v| v / n))
}

fn ref_depth_normal_loss(cam: &Camera, depth: &[f64], normals: &[[f64; 3]], wt: &[f64]) -> f64 {
    let (w, h) = (cam.w as usize, cam.h as usize);
    let mut s = 0.0;
    for y in 0..h {
        for x in 0..w {
            if let Some(n) = ref_depth_normal(cam, depth, x, y) {
                let t = normals[y * w + x];
                s += wt[y * w + x] * (1.0 - (n[0] * t[0] + n[1] * t[1] + n[2] * t[2]));
            }
        }
    }
    s / (w * h) as f64
}

// ---------- SSIM ----------

#[test]
fn ssim_of_an_image_with_itself_is_one() {
    let mut rng = SplitMix(1);
    let (w, h) = (37, 23);
    let a = random_image(&mut rng, w * h);
    // Exact in exact arithmetic; 1e-6 leaves room for f32 rounding of the mean.
    assert!((optim::ssim(&a, &a, w, h) - 1.0).abs() < 1e-6);
    assert!(optim::d_ssim(&a, &a, w, h).value.abs() < 1e-6);
    assert!((eval::ssim(&a, &a, w, h) - 1.0).abs() < 1e-6);
}

#[test]
fn ssim_matches_the_direct_reference() {
    let mut rng = SplitMix(2);
    // 7×5 is smaller than the window (every tap of the border code), 16×12 and 40×29 have an
    // interior; correlated pairs give mid-range SSIM, independent ones values near 0.
    for (w, h) in [(7, 5), (16, 12), (40, 29)] {
        let a = random_image(&mut rng, w * h);
        let b: Vec<[f32; 3]> = a
            .iter()
            .map(|p| p.map(|v| (v + rng.range(-0.15, 0.15)).clamp(0.0, 1.0)))
            .collect();
        let c = random_image(&mut rng, w * h);
        for (name, other) in [("correlated", &b), ("independent", &c)] {
            let fast = optim::ssim(&a, other, w, h) as f64;
            let slow = ref_ssim(&to3(&flat3(&a)), &to3(&flat3(other)), w, h);
            // f32 moments: ~1e-7 absolute error per moment, divided by σ² + C2 ≥ 1e-3 in the
            // worst pixel, averaged over all of them.
            assert!(
                (fast - slow).abs() < 1e-6,
                "{w}×{h} {name}: fast {fast} vs direct {slow}"
            );
        }
    }
}

#[test]
fn d_ssim_gradient_matches_finite_differences() {
    let mut rng = SplitMix(3);
    let (w, h) = (16, 12);
    let target = random_image(&mut rng, w * h);
    let rendered: Vec<[f32; 3]> = target
        .iter()
        .map(|p| p.map(|v| (v + rng.range(-0.2, 0.2)).clamp(0.0, 1.0)))
        .collect();
    let t64 = to3(&flat3(&target));
    let f = |x: &[f64]| (1.0 - ref_ssim(&to3(x), &t64, w, h)) / 2.0;
    let loss = optim::d_ssim(&rendered, &target, w, h);
    assert_value("D-SSIM", loss.value, f(&flat3(&rendered)), 1e-6);
    let fd = finite_differences(&flat3(&rendered), 1e-4, f);
    assert_grad("D-SSIM", &flat3(&loss.grad), &fd, 1e-4);
}

#[test]
fn rgb_loss_gradient_matches_finite_differences() {
    let mut rng = SplitMix(4);
    let (w, h) = (16, 12);
    let target = random_image(&mut rng, w * h);
    let rendered = perturbed(&mut rng, &target);
    let t64 = to3(&flat3(&target));
    let lambda = optim::LAMBDA_DSSIM;
    let f = |x: &[f64]| {
        let x3 = to3(x);
        (1.0 - lambda as f64) * ref_l1(&x3, &t64)
            + lambda as f64 * (1.0 - ref_ssim(&x3, &t64, w, h)) / 2.0
    };
    let loss = optim::rgb_loss(&rendered, &target, w, h, lambda);
    assert_value("L_RGB", loss.value, f(&flat3(&rendered)), 1e-6);
    let fd = finite_differences(&flat3(&rendered), 1e-4, f);
    assert_grad("L_RGB", &flat3(&loss.grad), &fd, 1e-4);
}

/// The display-space L_RGB against an f64 reference of the same composition, values from dark
/// (below the sRGB knee) to far above 1, and its gradient against central differences.
#[test]
fn display_rgb_loss_gradient_matches_finite_differences() {
    fn encode(x: f64) -> f64 {
        if x <= 0.003_130_8 {
            12.92 * x
        } else if x <= 1.0 {
            1.055 * x.powf(1.0 / 2.4) - 0.055
        } else {
            1.0 + 1.055 / 2.4 * (x - 1.0)
        }
    }
    let mut rng = SplitMix(14);
    let (w, h) = (16, 12);
    // Linear captures from 0 to 3 (sunlit patches), squared so dark values are common.
    let target: Vec<[f32; 3]> = (0..w * h)
        .map(|_| [0, 1, 2].map(|_| 3.0 * rng.f32() * rng.f32()))
        .collect();
    // Renders near the captures; kept off the knee and off 1, where the slope has a corner.
    let rendered: Vec<[f32; 3]> = perturbed(&mut rng, &target)
        .into_iter()
        .map(|c| {
            c.map(|v| {
                if (v - 1.0).abs() < 1e-3 || (v - 0.003).abs() < 5e-4 {
                    v + 0.01
                } else {
                    v
                }
            })
        })
        .collect();
    let t64: Vec<[f64; 3]> = target
        .iter()
        .map(|c| c.map(|v| encode((v as f64).clamp(0.0, 1.0))))
        .collect();
    let lambda = optim::LAMBDA_DSSIM as f64;
    let f = |x: &[f64]| {
        let x3: Vec<[f64; 3]> = to3(x).iter().map(|c| c.map(encode)).collect();
        (1.0 - lambda) * ref_l1(&x3, &t64) + lambda * (1.0 - ref_ssim(&x3, &t64, w, h)) / 2.0
    };
    let loss = optim::rgb_loss_display(&rendered, &target, w, h, optim::LAMBDA_DSSIM);
    assert_value("L_RGB display", loss.value, f(&flat3(&rendered)), 1e-5);
    let fd = finite_differences(&flat3(&rendered), 1e-5, f);
    assert_grad("L_RGB display", &flat3(&loss.grad), &fd, 1e-3);
    // The transfer function is continuous at the knee and at 1, and at 1 so is its slope.
    let (below, above) = (
        optim::display_encode(0.003_130_7),
        optim::display_encode(0.003_130_9),
    );
    assert!((below.0 - above.0).abs() < 1e-5);
    let (a, b) = (
        optim::display_encode(1.0 - 1e-6),
        optim::display_encode(1.0 + 1e-6),
    );
    assert!(
        (a.0 - b.0).abs() < 1e-5 && (a.1 - b.1).abs() < 1e-4,
        "{a:?} {b:?}"
    );
}

// ---------- per-pixel losses ----------

#[test]
fn l1_gradient_matches_finite_differences() {
    let mut rng = SplitMix(5);
    let target = random_image(&mut rng, 16 * 12);
    let rendered = perturbed(&mut rng, &target);
    let t64 = to3(&flat3(&target));
    let f = |x: &[f64]| ref_l1(&to3(x), &t64);
    let loss = optim::l1(&rendered, &target);
    assert_value("L1", loss.value, f(&flat3(&rendered)), 1e-6);
    let fd = finite_differences(&flat3(&rendered), 1e-4, f);
    assert_grad("L1", &flat3(&loss.grad), &fd, 1e-4);
}

#[test]
fn alpha_coverage_gradient_matches_finite_differences() {
    let mut rng = SplitMix(6);
    // Accumulated opacity in [0, 0.99] (away from the kink at 1), a few pixels above 1 to
    // check the sign (a compositor should not produce them, the loss still has to be right).
    let alpha: Vec<f32> = (0..16 * 12)
        .map(|i| {
            if i % 17 == 0 {
                rng.range(1.01, 1.1)
            } else {
                rng.range(0.0, 0.99)
            }
        })
        .collect();
    let f = |x: &[f64]| x.iter().map(|a| (a - 1.0).abs()).sum::<f64>() / x.len() as f64;
    let loss = optim::alpha_coverage(&alpha);
    assert_value("L_alpha", loss.value, f(&flat1(&alpha)), 1e-6);
    let fd = finite_differences(&flat1(&alpha), 1e-4, f);
    assert_grad("L_alpha", &flat1(&loss.grad), &fd, 1e-4);
}

#[test]
fn scale_regularization_gradient_matches_finite_differences() {
    let mut rng = SplitMix(7);
    let s_max = 0.05f32;
    // Half the surfels below s_max (zero loss), half above; components 0.01 apart (no tie).
    let scales: Vec<[f32; 2]> = (0..200)
        .map(|_| {
            let a = rng.range(0.01, 0.1);
            let b = if rng.f32() < 0.5 { a + 0.01 } else { a - 0.01 };
            let b = b.max(0.001);
            if (a - b).abs() < 0.009 {
                [a, a + 0.01]
            } else {
                [a, b]
            }
        })
        .collect();
    let flat: Vec<f64> = scales.iter().flat_map(|s| s.map(|v| v as f64)).collect();
    let f = |x: &[f64]| {
        x.chunks(2)
            .map(|s| (s[0].max(s[1]) / s_max as f64 - 1.0).max(0.0).powi(2))
            .sum::<f64>()
            / (x.len() / 2) as f64
    };
    let loss = optim::scale_regularization(&scales, s_max);
    assert!(loss.value > 0.0, "some surfels must exceed s_max");
    assert_value("L_s", loss.value, f(&flat), 1e-6);
    let fd = finite_differences(&flat, 1e-5, f);
    let analytic: Vec<f64> = loss.grad.iter().flat_map(|g| g.map(|v| v as f64)).collect();
    assert_grad("L_s", &analytic, &fd, 1e-4);
}

#[test]
fn depth_l1_gradients_match_finite_differences() {
    let mut rng = SplitMix(8);
    let n = 16 * 12;
    // Reference with holes (0 = no data), rendered depth at least 1 cm off.
    let reference: Vec<f32> = (0..n)
        .map(|i| if i % 7 == 3 { 0.0 } else { rng.range(1.0, 4.0) })
        .collect();
    let rendered: Vec<f32> = reference
        .iter()
        .map(|&d| {
            let e = rng.range(0.01, 0.3);
            (if rng.f32() < 0.5 { d + e } else { d - e }).max(0.05)
        })
        .collect();
    let conf: Vec<f32> = (0..n).map(|_| rng.range(0.2, 1.0)).collect();
    let r64 = flat1(&reference);
    let loss_of = |d: &[f64], c: &[f64]| {
        let (mut num, mut den) = (0.0, 0.0);
        for i in 0..d.len() {
            if r64[i] > 0.0 {
                num += c[i] * (d[i] - r64[i]).abs();
                den += c[i] * r64[i];
            }
        }
        num / (den + 1e-6)
    };
    let loss = optim::depth_l1(&rendered, &reference, Some(&conf));
    assert_value(
        "L_D",
        loss.value,
        loss_of(&flat1(&rendered), &flat1(&conf)),
        1e-6,
    );
    let c64 = flat1(&conf);
    let fd = finite_differences(&flat1(&rendered), 1e-4, |d| loss_of(d, &c64));
    assert_grad("L_D wrt depth", &flat1(&loss.grad), &fd, 1e-4);
    let d64 = flat1(&rendered);
    let fd = finite_differences(&c64, 1e-4, |c| loss_of(&d64, c));
    assert_grad("L_D wrt confidence", &flat1(&loss.grad_weight), &fd, 1e-4);
    // Holes get no gradient; no confidence means confidence 1.
    assert!((0..n).all(|i| reference[i] > 0.0 || loss.grad[i] == 0.0));
    let ones = vec![1.0f32; n];
    let a = optim::depth_l1(&rendered, &reference, None);
    let b = optim::depth_l1(&rendered, &reference, Some(&ones));
    assert_eq!(a, b);
}

fn random_unit(rng: &mut SplitMix) -> [f32; 3] {
    loop {
        let v = [
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        ];
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if n > 0.2 && n <= 1.0 {
            return v.map(|x| x / n);
        }
    }
}

#[test]
fn normal_loss_gradients_match_finite_differences() {
    let mut rng = SplitMix(9);
    let n = 16 * 12;
    let reference: Vec<[f32; 3]> = (0..n)
        .map(|i| {
            if i % 5 == 0 {
                [0.0; 3]
            } else {
                random_unit(&mut rng)
            }
        })
        .collect();
    let rendered: Vec<[f32; 3]> = (0..n).map(|_| random_unit(&mut rng)).collect();
    let weight: Vec<f32> = (0..n).map(|_| rng.range(0.0, 1.0)).collect();
    let t64 = to3(&flat3(&reference));
    let loss_of = |r: &[f64], w: &[f64]| {
        let r = to3(r);
        let mut s = 0.0;
        for i in 0..n {
            if t64[i] != [0.0; 3] {
                s += w[i] * (1.0 - (0..3).map(|c| r[i][c] * t64[i][c]).sum::<f64>());
            }
        }
        s / n as f64
    };
    let loss = optim::normal_loss(&rendered, &reference, Some(&weight));
    let (r64, w64) = (flat3(&rendered), flat1(&weight));
    assert_value("L_N", loss.value, loss_of(&r64, &w64), 1e-6);
    let fd = finite_differences(&r64, 1e-4, |r| loss_of(r, &w64));
    assert_grad("L_N wrt normals", &flat3(&loss.grad), &fd, 1e-4);
    let fd = finite_differences(&w64, 1e-4, |w| loss_of(&r64, w));
    assert_grad("L_N wrt weights", &flat1(&loss.grad_weight), &fd, 1e-4);
}

#[test]
fn env_tv_gradient_matches_finite_differences() {
    let mut rng = SplitMix(10);
    let (w, h) = (16, 8);
    // Texels drawn until they differ by ≥ 0.01 from their left, upper and (last column)
    // wrapped neighbour, so that no finite difference crosses a kink of |·|.
    let mut env = vec![[0.0f32; 3]; w * h];
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let near = |v: f32, env: &[[f32; 3]]| {
                    let mut others = vec![];
                    if x > 0 {
                        others.push(env[y * w + x - 1][c]);
                    }
                    if y > 0 {
                        others.push(env[(y - 1) * w + x][c]);
                    }
                    if x + 1 == w {
                        others.push(env[y * w][c]);
                    }
                    others.iter().any(|o| (o - v).abs() < 0.01)
                };
                let mut v = rng.range(0.0, 3.0);
                while near(v, &env) {
                    v = rng.range(0.0, 3.0);
                }
                env[y * w + x][c] = v;
            }
        }
    }
    let f = |x: &[f64]| ref_tv(&to3(x), w, h);
    let loss = optim::env_tv(&env, w, h);
    assert_value("L_TV", loss.value, f(&flat3(&env)), 1e-6);
    let fd = finite_differences(&flat3(&env), 1e-4, f);
    assert_grad("L_TV", &flat3(&loss.grad), &fd, 1e-4);
}

// ---------- depth-normal consistency ----------

#[test]
fn depth_normals_of_a_tilted_plane_are_the_plane_normal() {
    let cam = camera(32, 24);
    let (w, h) = (32usize, 24usize);
    let m = &cam.transform_matrix;
    let origin = glam::DVec3::new(m[0][3] as f64, m[1][3] as f64, m[2][3] as f64);
    let rot = |v: [f64; 3]| -> glam::DVec3 {
        glam::DVec3::from_array(std::array::from_fn(|r| {
            (0..3).map(|k| m[r][k] as f64 * v[k]).sum()
        }))
    };
    // A plane 3 m in front of the camera, tilted ~40° away from facing it.
    let forward = rot([0.0, 0.0, -1.0]);
    let facing = -forward;
    let normal = (facing + 0.6 * rot([1.0, 0.0, 0.0]) + 0.4 * rot([0.0, 1.0, 0.0])).normalize();
    let point = origin + 3.0 * forward;
    let depth: Vec<f32> = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            // Ray with camera-space z = −1: the ray parameter is the planar depth.
            let d = rot([
                (x + 0.5 - cam.cx as f64) / cam.fl_x as f64,
                -(y + 0.5 - cam.cy as f64) / cam.fl_y as f64,
                -1.0,
            ]);
            let t = normal.dot(point - origin) / normal.dot(d);
            assert!(t > 0.0, "the plane must be in front of every pixel");
            t as f32
        })
        .collect();
    let normals = optim::depth_normals(&depth, &cam);
    let mut checked = 0;
    for y in 0..h {
        for x in 0..w {
            let n = normals[y * w + x];
            if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                assert_eq!(n, [0.0; 3], "border pixels have no depth normal");
                continue;
            }
            // f32 points ~3 m, neighbour differences ~0.3 m: ~1e-6 relative error per
            // difference, so 1e-4 is loose but far below any real orientation error.
            let n = glam::DVec3::new(n[0] as f64, n[1] as f64, n[2] as f64);
            assert!(
                (n - normal).length() < 1e-4,
                "({x}, {y}): {n} vs plane normal {normal}"
            );
            checked += 1;
        }
    }
    assert_eq!(checked, (w - 2) * (h - 2));
}

#[test]
fn depth_normal_loss_gradients_match_finite_differences() {
    let cam = camera(16, 12);
    let (w, h) = (16usize, 12usize);
    let mut rng = SplitMix(11);
    // A smooth curved surface around 3 m with a little noise, and two holes (0 = no depth)
    // whose neighbours lose their normals.
    let depth: Vec<f32> = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            if i == 5 * w + 6 || i == 9 * w + 12 {
                return 0.0;
            }
            3.0 + 0.3 * (0.5 * x).sin() + 0.2 * (0.4 * y).cos() + rng.range(-0.01, 0.01)
        })
        .collect();
    let normals: Vec<[f32; 3]> = (0..w * h).map(|_| random_unit(&mut rng)).collect();
    let weight: Vec<f32> = (0..w * h).map(|_| rng.range(0.2, 1.0)).collect();
    let (d64, n64, w64) = (flat1(&depth), to3(&flat3(&normals)), flat1(&weight));

    let loss = optim::depth_normal_loss(&depth, &cam, &normals, Some(&weight));
    assert_value(
        "L_DN",
        loss.value,
        ref_depth_normal_loss(&cam, &d64, &n64, &w64),
        1e-6,
    );
    // The depth normals themselves against the f64 world-space reference.
    for y in 0..h {
        for x in 0..w {
            let got = loss.depth_normals[y * w + x];
            match ref_depth_normal(&cam, &d64, x, y) {
                None => assert_eq!(got, [0.0; 3], "({x}, {y}) has no depth normal"),
                Some(r) => {
                    let e = (0..3)
                        .map(|c| (got[c] as f64 - r[c]).abs())
                        .fold(0.0, f64::max);
                    assert!(e < 1e-4, "({x}, {y}): {got:?} vs {r:?}");
                }
            }
        }
    }
    assert_eq!(loss.depth_normals, optim::depth_normals(&depth, &cam));

    // d/d depth. A hole's own depth moving up from 0 would switch neighbours' normals on (a
    // discontinuity, not a gradient), so holes are only checked to have zero gradient.
    let fd = finite_differences(&d64, 1e-5, |d| ref_depth_normal_loss(&cam, d, &n64, &w64));
    let mask = |v: &[f64]| -> Vec<f64> {
        v.iter()
            .zip(&d64)
            .map(|(g, d)| if *d > 0.0 { *g } else { 0.0 })
            .collect()
    };
    assert_grad("L_DN wrt depth", &flat1(&loss.grad_depth), &mask(&fd), 1e-4);
    assert!((0..w * h).all(|i| depth[i] > 0.0 || loss.grad_depth[i] == 0.0));

    let fd = finite_differences(&flat3(&normals), 1e-4, |n| {
        ref_depth_normal_loss(&cam, &d64, &to3(n), &w64)
    });
    assert_grad("L_DN wrt normals", &flat3(&loss.grad_normal), &fd, 1e-4);
    let fd = finite_differences(&w64, 1e-4, |wt| ref_depth_normal_loss(&cam, &d64, &n64, wt));
    assert_grad("L_DN wrt weights", &flat1(&loss.grad_weight), &fd, 1e-4);
}

// ---------- Adam ----------

#[test]
fn adam_first_two_steps_by_hand() {
    // f(x) = x², x0 = 1, lr 0.1, β1 0.9, β2 0.999, ε 1e-15.
    // Step 1: g = 2, m = 0.2, v = 0.004, m̂ = 2, v̂ = 4: x1 = 1 − 0.1·2/2 = 0.9.
    // Step 2: g = 1.8, m = 0.18 + 0.18 = 0.36, v = 0.003996 + 0.00324 = 0.007236,
    //   m̂ = 0.36/0.19 = 1.8947368, v̂ = 0.007236/0.001999 = 3.6198099, √v̂ = 1.9025798,
    //   x2 = 0.9 − 0.1·1.8947368/1.9025798 = 0.8004122.
    let mut adam = Adam::new();
    let g = adam.add_group("x", 1, 1, Schedule::Constant { lr: 0.1 });
    let mut x = [1.0f32];
    let grad = [2.0 * x[0]];
    adam.step(g, &mut x, &grad);
    assert!((x[0] - 0.9).abs() < 1e-6, "x1 = {}", x[0]);
    let grad = [2.0 * x[0]];
    adam.step(g, &mut x, &grad);
    // The hand values carry 8 digits; f32 is good to ~1e-7 here.
    assert!((x[0] - 0.800_412_2).abs() < 1e-6, "x2 = {}", x[0]);
    assert_eq!(adam.group(g).steps(), 2);
    assert!((adam.group(g).exp_avg()[0] - 0.36).abs() < 1e-6);
    assert!((adam.group(g).exp_avg_sq()[0] - 0.007236).abs() < 1e-8);
}

#[test]
fn adam_converges_on_a_quadratic() {
    // f(x) = Σ a_i (x_i − b_i)² over two groups with different curvatures and learning rates.
    let mut rng = SplitMix(12);
    let (a, b): (Vec<f32>, Vec<f32>) = (0..64)
        .map(|_| (rng.range(0.1, 10.0), rng.range(-2.0, 2.0)))
        .unzip();
    let mut adam = Adam::new();
    let g0 = adam.add_group(
        "position",
        48,
        3,
        Schedule::Exponential {
            lr_init: 0.05,
            lr_final: 1e-4,
            steps: 3000,
        },
    );
    let g1 = adam.add_group("opacity", 16, 1, Schedule::Constant { lr: 0.01 });
    let mut x = vec![0.0f32; 64];
    for _ in 0..3000 {
        let grad: Vec<f32> = (0..64).map(|i| 2.0 * a[i] * (x[i] - b[i])).collect();
        let (p0, p1) = x.split_at_mut(48);
        adam.step(g0, p0, &grad[..48]);
        adam.step(g1, p1, &grad[48..]);
    }
    // Decayed steps end at lr 1e-4, so Adam's oscillation around the minimum is ≲ 1e-3.
    for i in 0..64 {
        assert!((x[i] - b[i]).abs() < 2e-3, "x[{i}] = {} vs {}", x[i], b[i]);
    }
}

/// [`Adam::step_shared`] against an f64 reference of its definition over 20 steps of random
/// gradients (one second moment, the mean of g² over the group, shared by every parameter; the
/// bias corrections and the first moment as per-parameter Adam), with the step limit active on
/// the parameter whose gradient is 30× the others': f32 state against f64, ≤ 1e-5 relative.
/// Then what it is for: with gradients in a fixed ratio of 10, the parameters' moves keep that
/// ratio, where per-parameter Adam moves both alike.
#[test]
fn adam_shared_moment_matches_its_reference_and_keeps_gradient_ratios() {
    let (n, lr, max_step) = (16usize, 0.05f64, 3.0f64);
    let mut rng = SplitMix(31);
    let mut adam = Adam::new();
    let g = adam.add_group("env", n, 1, Schedule::Constant { lr: lr as f32 });
    let mut x = vec![0.0f32; n];
    let (mut xr, mut m, mut v) = (vec![0.0f64; n], vec![0.0f64; n], 0.0f64);
    let mut limited = 0;
    for t in 1..=20 {
        let grad: Vec<f32> = (0..n)
            .map(|i| rng.range(-1.0, 1.0) * if i == 0 { 30.0 } else { 1.0 })
            .collect();
        adam.step_shared(g, &mut x, &grad, max_step as f32);
        let mean_sq = grad.iter().map(|&g| (g as f64).powi(2)).sum::<f64>() / n as f64;
        v = 0.999 * v + 0.001 * mean_sq;
        let (bc1, bc2) = (1.0 - 0.9f64.powi(t), 1.0 - 0.999f64.powi(t));
        for i in 0..n {
            m[i] = 0.9 * m[i] + 0.1 * grad[i] as f64;
            let d = lr / bc1 * m[i] / ((v / bc2).sqrt() + 1e-15);
            limited += (d.abs() > max_step * lr) as usize;
            xr[i] -= d.clamp(-max_step * lr, max_step * lr);
        }
        for i in 0..n {
            let tol = 1e-5 * xr[i].abs().max(lr);
            assert!(
                (x[i] as f64 - xr[i]).abs() < tol,
                "step {t}, parameter {i}: {} vs reference {}",
                x[i],
                xr[i]
            );
        }
    }
    assert!(
        limited > 0,
        "the limit was never reached: the test does not check it"
    );

    let moves = |shared: bool| {
        let mut adam = Adam::new();
        let g = adam.add_group("env", 2, 1, Schedule::Constant { lr: 0.01 });
        let mut x = [0.0f32; 2];
        for _ in 0..50 {
            if shared {
                adam.step_shared(g, &mut x, &[1.0, 0.1], 100.0);
            } else {
                adam.step(g, &mut x, &[1.0, 0.1]);
            }
        }
        x[0] / x[1]
    };
    assert!(
        (moves(true) - 10.0).abs() < 1e-3,
        "shared: ratio {}",
        moves(true)
    );
    assert!(
        (moves(false) - 1.0).abs() < 1e-3,
        "per parameter: ratio {}",
        moves(false)
    );
}

#[test]
fn schedule_endpoints() {
    let s = Schedule::Exponential {
        lr_init: 1.6e-4,
        lr_final: 1.6e-6,
        steps: 30_000,
    };
    // Within f32 rounding of exp(ln …).
    let close = |a: f32, b: f32| (a - b).abs() <= 1e-6 * b;
    assert!(close(s.lr(0), 1.6e-4));
    assert!(close(s.lr(30_000), 1.6e-6));
    assert!(close(s.lr(90_000), 1.6e-6), "constant after the end");
    assert!(close(s.lr(15_000), 1.6e-5), "geometric mean half way");
    assert!(s.lr(1) < s.lr(0) && s.lr(29_999) > s.lr(30_000));
    assert_eq!(Schedule::Constant { lr: 0.025 }.lr(12345), 0.025);
}

#[test]
fn densify_and_prune_keep_the_right_moments() {
    let mut adam = Adam::new();
    let g = adam.add_group("position", 9, 3, Schedule::Constant { lr: 0.1 });
    let mut p: Vec<f32> = (0..9).map(|i| i as f32).collect();
    for s in 0..3 {
        let grad: Vec<f32> = (0..9).map(|i| (i * 7 + s) as f32 * 0.1 - 2.0).collect();
        adam.step(g, &mut p, &grad);
    }
    let (m, v) = (
        adam.group(g).exp_avg().to_vec(),
        adam.group(g).exp_avg_sq().to_vec(),
    );
    // Prune point 1, reorder: keep points 2 and 0.
    adam.keep_points(g, &[2, 0]);
    assert_eq!(adam.group(g).exp_avg(), [&m[6..9], &m[0..3]].concat());
    assert_eq!(adam.group(g).exp_avg_sq(), [&v[6..9], &v[0..3]].concat());
    // Densify: two new points with zero moments; the step counter goes on.
    adam.append_points(g, 2);
    assert_eq!(adam.group(g).points(), 4);
    assert_eq!(&adam.group(g).exp_avg()[..6], [&m[6..9], &m[0..3]].concat());
    assert!(adam.group(g).exp_avg()[6..].iter().all(|&x| x == 0.0));
    assert!(adam.group(g).exp_avg_sq()[6..].iter().all(|&x| x == 0.0));
    assert_eq!(adam.group(g).steps(), 3);
    // A new point's first update with bias correction at t = 4 is lr·(1−β1)/(1−β1⁴) /
    // (√((1−β2)/(1−β2⁴)))·sign(g), not lr: 3DGS's behaviour.
    let mut q = vec![0.0f32; 12];
    let mut grad = vec![0.0f32; 12];
    grad[9] = 1.0;
    adam.step(g, &mut q, &grad);
    let expect =
        0.1 * (0.1 / (1.0 - 0.9f64.powi(4))) / (0.001f64 / (1.0 - 0.999f64.powi(4))).sqrt();
    assert!(
        ((-q[9]) as f64 - expect).abs() < 1e-5 * expect,
        "{} vs {expect}",
        -q[9]
    );
}

#[test]
fn adam_state_round_trips_and_bad_checkpoints_are_errors() {
    let mut adam = Adam::new();
    let g = adam.add_group(
        "position",
        6,
        3,
        Schedule::Exponential {
            lr_init: 1e-3,
            lr_final: 1e-5,
            steps: 100,
        },
    );
    let mut p = vec![0.5f32; 6];
    adam.step(g, &mut p, &[0.3, -0.1, 0.7, 1e-3, 2.0, -5.0]);
    let json = serde_json::to_string(&adam).unwrap();
    let back: Adam = serde_json::from_str(&json).unwrap();
    assert_eq!(back, adam);
    let file = Path::new("ckpt/optimizer.json");
    back.validate(file).unwrap();
    assert_eq!(back.expect_group(file, "position", 6).unwrap(), g);

    let err = back
        .expect_group(file, "position", 9)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("ckpt/optimizer.json") && err.contains("expected 9 values"),
        "{err}"
    );
    let err = back.expect_group(file, "sh", 9).unwrap_err().to_string();
    assert!(err.contains("expected a group named sh"), "{err}");

    let broken = json.replacen("\"exp_avg_sq\":[", "\"exp_avg_sq\":[1.0,", 1);
    let bad: Adam = serde_json::from_str(&broken).unwrap();
    let e = bad.validate(file).unwrap_err();
    assert!(e.is_user_error());
    let err = e.to_string();
    assert!(
        err.contains("exp_avg_sq") && err.contains("expected 6 values"),
        "{err}"
    );
    let bad: Adam = serde_json::from_str(&json.replacen("\"width\":3", "\"width\":4", 1)).unwrap();
    assert!(bad
        .validate(file)
        .unwrap_err()
        .to_string()
        .contains("width"));
}

// ---------- metrics ----------

#[test]
fn psnr_and_srgb() {
    let a = vec![[0.2f32, 0.5, 0.7]; 10];
    let b: Vec<[f32; 3]> = a.iter().map(|p| p.map(|v| v + 0.1)).collect();
    // MSE 0.01 → 20 dB (to f32 rounding of the 0.1 offsets).
    assert!((eval::psnr(&a, &b) - 20.0).abs() < 1e-4);
    assert_eq!(eval::psnr(&a, &a), f64::INFINITY);
    // Clamping: 1.5 and 3.0 are both 1, −0.2 is 0.
    let c = vec![[1.5f32, 3.0, -0.2]; 4];
    let d = vec![[1.0f32, 1.0, 0.0]; 4];
    assert_eq!(eval::psnr(&c, &d), f64::INFINITY);
    assert_eq!(eval::psnr_srgb(&c, &d), f64::INFINITY);
    // sRGB: 0.5 linear → 0.735357 (IEC 61966-2-1), linear segment below 0.0031308.
    assert!((srgb_encode(0.5) - 0.735_357).abs() < 1e-5);
    assert!((srgb_encode(0.002) - 0.025_84).abs() < 1e-6);
    assert_eq!(srgb_encode(1.0), 1.0);
    // A dark offset is larger after encoding: 0.01 vs 0.02 linear.
    let e = vec![[0.01f32; 3]; 4];
    let f = vec![[0.02f32; 3]; 4];
    let d_srgb = (srgb_encode(0.02) - srgb_encode(0.01)) as f64;
    assert!((eval::psnr(&e, &f) - 40.0).abs() < 1e-3);
    assert!((eval::psnr_srgb(&e, &f) + 20.0 * d_srgb.log10()).abs() < 1e-3);
    // sRGB SSIM is SSIM of the encoded images.
    let mut rng = SplitMix(13);
    let (w, h) = (20, 15);
    let g = random_image(&mut rng, w * h);
    let k = random_image(&mut rng, w * h);
    let enc = |i: &[[f32; 3]]| -> Vec<[f32; 3]> { i.iter().map(|p| p.map(srgb_encode)).collect() };
    assert_eq!(
        eval::ssim_srgb(&g, &k, w, h),
        eval::ssim(&enc(&g), &enc(&k), w, h)
    );
}

#[test]
fn depth_error_on_valid_pixels() {
    let reference = [1.0f32, 2.0, 0.0, 4.0, 5.0, f32::NAN];
    let rendered = [1.5f32, 2.0, 9.0, 3.0, 0.0, 1.0];
    // Valid: pixels 0, 1, 3, 4 with errors 0.5, 0, 1, 5.
    let e = eval::depth_error(&rendered, &reference);
    assert_eq!(e.count, 4);
    assert!((e.mean - 1.625).abs() < 1e-12);
    assert!((e.median - 0.75).abs() < 1e-12);
    let e = eval::depth_error(&rendered[..4], &reference[..4]);
    assert_eq!((e.count, e.median), (3, 0.5));
    assert!(eval::depth_error(&[1.0], &[0.0]).mean.is_nan());
}

// ---------- timing (run with --ignored; prints, asserts nothing about speed) ----------

#[test]
#[ignore]
fn bench_d_ssim_128() {
    let mut rng = SplitMix(14);
    let (w, h) = (128, 128);
    let a = random_image(&mut rng, w * h);
    let b = random_image(&mut rng, w * h);
    let mut sink = 0.0f32;
    for _ in 0..5 {
        sink += optim::d_ssim(&a, &b, w, h).value;
    }
    let reps = 200;
    let t = std::time::Instant::now();
    for _ in 0..reps {
        sink += optim::d_ssim(&a, &b, w, h).grad[w * h / 2][1];
    }
    let dt = t.elapsed().as_secs_f64() / reps as f64;
    println!(
        "D-SSIM forward+backward 128x128 RGB: {:.3} ms ({} rayon threads) [{sink}]",
        dt * 1e3,
        rayon::current_num_threads()
    );
}
