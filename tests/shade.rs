//! Shading building blocks: BRDF, environment map, Sobol sampler.
//!
//! How the tests decide, and their tolerances:
//! - Densities integrate to one: midpoint quadrature in f64. For the BRDF the grid is polar
//!   about the mirror direction with θ' = π s² (dense where the GGX peak is), so lobes down to
//!   roughness 0.2 are resolved to ~1e-4; the mass a VNDF sample loses below the horizon is
//!   computed from an f64 reference density and must match both the quadrature and the rate of
//!   `None` samples. For the environment the grid is aligned with the texels.
//! - Densities match their samples: Pearson's chi-square on a (cos θ, φ) or (θ, φ) grid, cells
//!   with expected count < 5 pooled, expected counts from per-cell quadrature, fixed seeds,
//!   rejected below p = 1e-3 (a correct sampler fails one seed in a thousand).
//! - `eval / pdf` of a sample equals its weight to 1e-4 relative (f32 arithmetic).
//! - The f32 BRDF against a transcription of glTF's formulas in f64: 1e-4 relative.
//!
//! Sample counts are modest so the file runs in a few seconds in the debug profile.

mod common;

use glam::{DVec3, Vec3};
use lightfuse::scene::material::{self, Material};
use lightfuse::scene::Environment;
use lightfuse::shade::brdf;
use lightfuse::shade::envmap::{self, EnvMap};
use lightfuse::shade::sobol::Sampler;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use std::f64::consts::PI;

// ------------------------------------------------------------------------ statistics helpers

/// ln Γ(x), Lanczos (g = 7, n = 9), |error| < 1e-13 for x > 0.
fn ln_gamma(x: f64) -> f64 {
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        return (PI / (PI * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularised upper incomplete gamma Q(a, x) (series below a + 1, Lentz's continued fraction
/// above, as in Numerical Recipes' gammq).
fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let ln_pre = -x + a * x.ln() - ln_gamma(a);
    if x < a + 1.0 {
        let (mut sum, mut term, mut ap) = (1.0 / a, 1.0 / a, a);
        for _ in 0..10_000 {
            ap += 1.0;
            term *= x / ap;
            sum += term;
            if term.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        1.0 - sum * ln_pre.exp()
    } else {
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..10_000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        ln_pre.exp() * h
    }
}

/// Pearson's chi-square p-value of `observed` against `expected` counts; cells with expected
/// < 5 are pooled into one cell. Returns (p, statistic, degrees of freedom).
fn chi_square(observed: &[f64], expected: &[f64]) -> (f64, f64, usize) {
    let (mut stat, mut cells) = (0.0, 0usize);
    let (mut pool_o, mut pool_e) = (0.0, 0.0);
    for (&o, &e) in observed.iter().zip(expected) {
        if e < 5.0 {
            pool_o += o;
            pool_e += e;
        } else {
            stat += (o - e) * (o - e) / e;
            cells += 1;
        }
    }
    if pool_e > 0.0 {
        stat += (pool_o - pool_e) * (pool_o - pool_e) / pool_e;
        cells += 1;
    } else {
        assert_eq!(pool_o, 0.0, "samples where the density is zero");
    }
    let dof = cells - 1;
    (gamma_q(dof as f64 / 2.0, stat / 2.0), stat, dof)
}

#[test]
fn chi_square_survival_matches_tables() {
    // Standard table values: P(χ²_k > x).
    for (k, x, q) in [
        (1.0, 3.841_458_820_694_124, 0.05),
        (10.0, 18.307_038_053_275_146, 0.05),
        (100.0, 135.806_722_565_7, 0.01),
        (4.0, 2.0, 0.735_758_882_342_884_6),
    ] {
        let got = gamma_q(k / 2.0, x / 2.0);
        assert!((got - q).abs() < 1e-9, "k={k} x={x}: {got} vs {q}");
    }
}

fn rel_close(a: f64, b: f64, rel: f64, abs: f64) -> bool {
    (a - b).abs() <= rel * a.abs().max(b.abs()) + abs
}

// ------------------------------------------------------------------------ f64 BRDF reference

/// glTF 2.0 Appendix B, straight from the spec's formulas, in f64 and the local frame (n = +z):
/// mix(fresnel_mix(0.04; diffuse, specular), conductor_fresnel(base; specular), metallic).
fn ref_f(wo: DVec3, wi: DVec3, base: [f64; 3], metallic: f64, roughness: f64) -> [f64; 3] {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return [0.0; 3];
    }
    let a = (roughness * roughness).max(1e-3);
    let a2 = a * a;
    let h = (wo + wi).normalize();
    let d = a2 / (PI * (h.z * h.z * (a2 - 1.0) + 1.0).powi(2));
    let v = 0.5
        / (wi.z * (wo.z * wo.z * (1.0 - a2) + a2).sqrt()
            + wo.z * (wi.z * wi.z * (1.0 - a2) + a2).sqrt());
    let s = (1.0 - wo.dot(h).abs()).powi(5);
    let specular = d * v;
    let f_d = 0.04 + 0.96 * s;
    base.map(|c| {
        let dielectric = (1.0 - f_d) * c / PI + f_d * specular;
        let metal = (c + (1.0 - c) * s) * specular;
        (1.0 - metallic) * dielectric + metallic * metal
    })
}

/// The VNDF-reflected density in f64, *not* clipped at the horizon: it integrates to one over
/// the whole sphere, and its mass below the horizon is what `sample` returns as `None`.
fn ref_vndf_unclipped(wo: DVec3, wi: DVec3, alpha: f64) -> f64 {
    let h = (wo + wi).normalize();
    if h.z <= 0.0 || wo.dot(h) <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let g1 = 2.0 * wo.z / (wo.z + (a2 + (1.0 - a2) * wo.z * wo.z).sqrt());
    let d = a2 / (PI * (h.z * h.z * (a2 - 1.0) + 1.0).powi(2));
    g1 * d / (4.0 * wo.z)
}

fn material(base: f32, metallic: f32, roughness: f32) -> Material {
    Material {
        base_color: [base, base * 0.8, base * 0.6],
        metallic,
        roughness,
    }
}

fn view(cos_o: f64) -> DVec3 {
    DVec3::new((1.0 - cos_o * cos_o).sqrt(), 0.0, cos_o)
}

/// ∫ g(wi) dω over the sphere on a polar grid about `axis`, θ' = π s² (s midpoint, n_s rows),
/// dω = sin θ' · 2πs ds dφ.
fn integrate_about(axis: DVec3, n_s: usize, n_phi: usize, mut g: impl FnMut(DVec3) -> f64) -> f64 {
    let (t, b) = axis.any_orthonormal_pair();
    let (ds, dphi) = (1.0 / n_s as f64, 2.0 * PI / n_phi as f64);
    let mut sum = 0.0;
    for i in 0..n_s {
        let s = (i as f64 + 0.5) * ds;
        let theta = PI * s * s;
        let jac = theta.sin() * 2.0 * PI * s * ds * dphi;
        let (st, ct) = theta.sin_cos();
        for j in 0..n_phi {
            let phi = (j as f64 + 0.5) * dphi;
            let wi = axis * ct + (t * phi.cos() + b * phi.sin()) * st;
            sum += g(wi) * jac;
        }
    }
    sum
}

fn to_f32(v: DVec3) -> Vec3 {
    v.as_vec3()
}

/// (roughness, metallic, cos θo) of the BRDF checks: smooth to rough, dielectric to metal,
/// normal to grazing view.
const BRDF_CASES: [(f32, f32, f64); 7] = [
    (0.2, 0.0, 0.95),
    (0.3, 1.0, 0.5),
    (0.5, 0.5, 0.8),
    (0.5, 0.0, 0.15),
    (0.8, 1.0, 0.3),
    (1.0, 0.0, 1.0),
    (1.0, 0.3, 0.05),
];

#[test]
fn brdf_matches_f64_transcription_of_gltf() {
    let mut rng = Pcg64::seed_from_u64(1);
    let mut checked = 0;
    for _ in 0..2000 {
        let m = Material {
            base_color: [rng.random(), rng.random(), rng.random()],
            metallic: rng.random(),
            roughness: rng.random_range(0.05..1.0),
        };
        let wo = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random(),
        )
        .normalize();
        let wi = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random(),
        )
        .normalize();
        let got = brdf::eval_f(Vec3::Z, to_f32(wo), to_f32(wi), &m);
        let want = ref_f(
            wo,
            wi,
            m.base_color.map(f64::from),
            m.metallic as f64,
            m.roughness as f64,
        );
        for c in 0..3 {
            assert!(
                rel_close(got[c] as f64, want[c], 1e-4, 1e-7),
                "{m:?} wo {wo} wi {wi}: {got:?} vs {want:?}"
            );
        }
        checked += 1;
        // The lobes add up, and a turned frame gives the same value.
        let n = Vec3::new(0.3, -0.4, 0.866).normalize();
        let fr = brdf::Frame::new(n);
        let got2 = brdf::eval_f(n, fr.to_world(to_f32(wo)), fr.to_world(to_f32(wi)), &m);
        for c in 0..3 {
            assert!(rel_close(got2[c] as f64, want[c], 1e-3, 1e-6));
        }
    }
    assert_eq!(checked, 2000);
}

/// The material adjoint `eval_f_cos_grad` against central differences of the f64 reference
/// (ε = 1e-6 in f64: truncation ~1e-12, rounding ~1e-10, far below the f32 adjoint's 1e-4),
/// with a random upstream gradient. Roughness below √MIN_ALPHA sits on α's clamp, where
/// the value does not depend on it and the adjoint must say zero.
#[test]
fn brdf_material_adjoint_matches_f64_finite_differences() {
    let mut rng = Pcg64::seed_from_u64(2);
    for k in 0..2000 {
        let roughness = if k % 10 == 0 {
            0.02
        } else {
            rng.random_range(0.1..1.0)
        };
        let m = Material {
            base_color: [rng.random(), rng.random(), rng.random()],
            metallic: rng.random(),
            roughness,
        };
        let up = |rng: &mut Pcg64| {
            DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(0.05..1.0),
            )
            .normalize()
        };
        let (wo, wi) = (up(&mut rng), up(&mut rng));
        let g: [f32; 3] = [
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ];
        let got = brdf::eval_f_cos_grad(Vec3::Z, to_f32(wo), to_f32(wi), &m, g);
        let (wo, wi) = (to_f32(wo).as_dvec3(), to_f32(wi).as_dvec3());
        let value = |base: [f64; 3], metallic: f64, roughness: f64| -> f64 {
            let f = ref_f(wo, wi, base, metallic, roughness);
            (0..3).map(|c| g[c] as f64 * f[c] * wi.z).sum()
        };
        let base = m.base_color.map(f64::from);
        let (mt, r) = (m.metallic as f64, m.roughness as f64);
        let e = 1e-6;
        let central = |f: &dyn Fn(f64) -> f64| (f(e) - f(-e)) / (2.0 * e);
        let mut want = [0.0f64; 5];
        for c in 0..3 {
            want[c] = central(&|d| {
                let mut b = base;
                b[c] += d;
                value(b, mt, r)
            });
        }
        want[3] = central(&|d| value(base, mt + d, r));
        want[4] = central(&|d| value(base, mt, r + d));
        let got = [
            got.base_color[0],
            got.base_color[1],
            got.base_color[2],
            got.metallic,
            got.roughness,
        ];
        let scale = want.iter().map(|v| v.abs()).fold(0.0, f64::max);
        for i in 0..5 {
            assert!(
                rel_close(got[i] as f64, want[i], 2e-3, 2e-4 * scale + 1e-7),
                "{m:?} wo {wo} wi {wi}, parameter {i}: {got:?} vs {want:?}"
            );
        }
        if roughness * roughness < material::MIN_ALPHA {
            assert_eq!(got[4], 0.0);
        }
    }
}

#[test]
fn brdf_pdf_integrates_to_one_less_the_mass_lost_below_the_horizon() {
    for (roughness, metallic, cos_o) in BRDF_CASES {
        let m = material(0.9, metallic, roughness);
        let wo = view(cos_o);
        let mirror = DVec3::new(-wo.x, -wo.y, wo.z);
        let integral = integrate_about(mirror, 600, 256, |wi| {
            brdf::pdf(Vec3::Z, to_f32(wo), to_f32(wi), &m) as f64
        });
        // Lost mass: the unclipped VNDF density below the horizon, in f64.
        let alpha = m.alpha() as f64;
        let below = integrate_about(mirror, 600, 256, |wi| {
            if wi.z <= 0.0 {
                ref_vndf_unclipped(wo, wi, alpha)
            } else {
                0.0
            }
        });
        let unclipped = integrate_about(mirror, 600, 256, |wi| ref_vndf_unclipped(wo, wi, alpha));
        let p_spec = brdf::specular_probability(cos_o as f32, &m) as f64;
        let expected = 1.0 - p_spec * below;
        println!(
            "r {roughness} m {metallic} cos {cos_o}: ∫pdf = {integral:.6}, 1 − lost = \
             {expected:.6}, ∫VNDF over sphere = {unclipped:.6}"
        );
        assert!((unclipped - 1.0).abs() < 2e-3, "VNDF reference {unclipped}");
        assert!(
            (integral - expected).abs() < 2e-3,
            "r {roughness} m {metallic} cos {cos_o}: {integral} vs {expected}"
        );
    }
}

#[test]
fn brdf_samples_follow_pdf_chi_square_and_weights_are_eval_over_pdf() {
    let n_samples = if cfg!(debug_assertions) {
        60_000
    } else {
        400_000
    };
    let (n_cos, n_phi) = (16usize, 32usize);
    for (case, (roughness, metallic, cos_o)) in BRDF_CASES.into_iter().enumerate() {
        let m = material(0.9, metallic, roughness);
        let wo = to_f32(view(cos_o));
        // Rotate the whole configuration: the frame code is exercised too.
        let n = Vec3::new(0.2, 0.9, -0.3).normalize();
        let fr = brdf::Frame::new(n);
        let wo_w = fr.to_world(wo);
        let mut rng = Pcg64::seed_from_u64(100 + case as u64);
        let mut observed = vec![0.0f64; n_cos * n_phi + 1];
        let mut worst_weight = 0.0f64;
        for _ in 0..n_samples {
            let u = [rng.random::<f32>(), rng.random::<f32>()];
            match brdf::sample(n, wo_w, &m, u, rng.random()) {
                None => observed[n_cos * n_phi] += 1.0,
                Some(s) => {
                    let f = brdf::eval_f_cos(n, wo_w, s.wi, &m);
                    let p = brdf::pdf(n, wo_w, s.wi, &m);
                    assert!(
                        rel_close(p as f64, s.pdf as f64, 1e-4, 0.0),
                        "{p} vs {}",
                        s.pdf
                    );
                    for (fc, wc) in f.iter().zip(s.weight) {
                        let want = *fc as f64 / p as f64;
                        let err = (wc as f64 - want).abs() / want.abs().max(1e-12);
                        worst_weight = worst_weight.max(err);
                    }
                    let wl = fr.to_local(s.wi);
                    let ic = (((1.0 - wl.z) * n_cos as f32) as usize).min(n_cos - 1);
                    let phi = wl.y.atan2(wl.x).rem_euclid(2.0 * std::f32::consts::PI);
                    let ip = ((phi / (2.0 * std::f32::consts::PI) * n_phi as f32) as usize)
                        .min(n_phi - 1);
                    observed[ic * n_phi + ip] += 1.0;
                }
            }
        }
        assert!(
            worst_weight < 1e-4,
            "case {case}: weight vs eval/pdf {worst_weight}"
        );
        // Expected counts: 12x12 midpoint quadrature per cell, in (cos θ, φ).
        let sub = 12;
        let mut expected = vec![0.0f64; n_cos * n_phi + 1];
        for ic in 0..n_cos {
            for ip in 0..n_phi {
                let mut acc = 0.0;
                for a in 0..sub {
                    let z = 1.0 - (ic as f64 + (a as f64 + 0.5) / sub as f64) / n_cos as f64;
                    let r = (1.0 - z * z).max(0.0).sqrt();
                    for b in 0..sub {
                        let phi =
                            2.0 * PI * (ip as f64 + (b as f64 + 0.5) / sub as f64) / n_phi as f64;
                        let wi = DVec3::new(r * phi.cos(), r * phi.sin(), z);
                        acc += brdf::pdf(Vec3::Z, wo, to_f32(wi), &m) as f64;
                    }
                }
                let cell = (1.0 / n_cos as f64) * (2.0 * PI / n_phi as f64);
                expected[ic * n_phi + ip] = acc / (sub * sub) as f64 * cell * n_samples as f64;
            }
        }
        let in_bins: f64 = expected.iter().sum();
        expected[n_cos * n_phi] = (n_samples as f64 - in_bins).max(0.0);
        let (p, stat, dof) = chi_square(&observed, &expected);
        println!(
            "BRDF r {roughness} m {metallic} cos {cos_o}: chi² {stat:.1} dof {dof} p {p:.3e}, \
             None {:.4}, worst |weight − f cos/pdf| {worst_weight:.1e}",
            observed[n_cos * n_phi] / n_samples as f64
        );
        assert!(
            p > 1e-3,
            "case {case}: chi-square p = {p} (stat {stat}, dof {dof})"
        );
    }
}

#[test]
fn brdf_white_furnace() {
    let white = |metallic: f32, roughness: f32| Material {
        base_color: [1.0; 3],
        metallic,
        roughness,
    };
    // One Sobol stream holds at most MAX_SAMPLES (2^16) samples.
    let n_mc = if cfg!(debug_assertions) {
        20_000
    } else {
        lightfuse::shade::sobol::MAX_SAMPLES
    };
    let albedo_quad = |m: &Material, cos_o: f64, lobe: usize| {
        let wo = view(cos_o);
        let mirror = DVec3::new(-wo.x, 0.0, wo.z);
        integrate_about(mirror, 500, 192, |wi| {
            if wi.z <= 0.0 {
                return 0.0;
            }
            let l = brdf::eval_lobes(Vec3::Z, to_f32(wo), to_f32(wi), m);
            let v = match lobe {
                0 => l.diffuse[1],
                1 => l.specular[1],
                _ => l.diffuse[1] + l.specular[1],
            };
            v as f64 * wi.z
        })
    };
    let albedo_mc = |m: &Material, cos_o: f64| {
        let wo = to_f32(view(cos_o));
        let s = Sampler::new(7, 11);
        let mut sum = 0.0;
        for i in 0..n_mc {
            let [u0, u1] = s.get_2d(i, 0);
            if let Some(smp) = brdf::sample(Vec3::Z, wo, m, [u0, u1], s.get(i, 2)) {
                sum += smp.weight[1] as f64;
            }
        }
        sum / n_mc as f64
    };
    // Plain Lambert (the diffuse lobe with its Fresnel weight removed) is exactly 1.
    let lambert = integrate_about(DVec3::Z, 500, 192, |wi| wi.z.max(0.0) / PI);
    assert!((lambert - 1.0).abs() < 1e-4, "∫cos/π = {lambert}");

    // White metal: E(μ) ≤ 1 for every roughness and view, → 1 as roughness → 0.
    let mut prev_normal = 0.0;
    for roughness in [1.0f32, 0.7, 0.5, 0.3, 0.2] {
        for cos_o in [1.0, 0.7, 0.4, 0.1] {
            let m = white(1.0, roughness);
            let q = albedo_quad(&m, cos_o, 2);
            let mc = albedo_mc(&m, cos_o);
            println!("white metal r {roughness} μ {cos_o}: E quad {q:.5} MC {mc:.5}");
            assert!(q <= 1.0 + 1e-3, "metal r {roughness} μ {cos_o}: E = {q}");
            assert!((q - mc).abs() < 5e-3, "quadrature {q} vs MC {mc}");
            if cos_o == 1.0 {
                assert!(q >= prev_normal - 1e-4, "E(1) grows as roughness falls");
                prev_normal = q;
            }
        }
    }
    for roughness in [0.1f32, 0.0] {
        let mc = albedo_mc(&white(1.0, roughness), 1.0);
        println!("white metal r {roughness} μ 1: E MC {mc:.5}");
        assert!((mc - 1.0).abs() < 3e-3, "smooth white metal E(1) = {mc}");
    }

    // White dielectric: the diffuse lobe gives 1 − (Fresnel-reflected share) < 1; the total is
    // ≤ 1 at normal incidence. At oblique views glTF's (1 − F(o·h)) layering lets it exceed 1
    // (1.33 at μ = 0.05, roughness 0.3; printed, not asserted).
    for roughness in [1.0f32, 0.5, 0.3] {
        for cos_o in [1.0, 0.7, 0.5, 0.2, 0.05] {
            let m = white(0.0, roughness);
            let (d, s, t) = (
                albedo_quad(&m, cos_o, 0),
                albedo_quad(&m, cos_o, 1),
                albedo_quad(&m, cos_o, 2),
            );
            let mc = albedo_mc(&m, cos_o);
            println!(
                "white dielectric r {roughness} μ {cos_o}: E diffuse {d:.5} specular {s:.5} \
                 total {t:.5} (MC {mc:.5})"
            );
            assert!(d < 1.0, "diffuse lobe {d}");
            assert!((t - mc).abs() < 1e-2, "quadrature {t} vs MC {mc}");
            if cos_o == 1.0 {
                assert!(t <= 1.0 + 1e-3, "dielectric r {roughness} μ 1: E = {t}");
            }
            // Each lobe alone conserves energy; their sum need not at oblique views.
            assert!(s <= 1.0, "specular lobe {s}");
        }
    }
}

// ------------------------------------------------------------------------ environment map

#[test]
fn env_mapping_matches_cycles() {
    // Cycles (kernel/camera/projection.h): with b the Blender direction,
    //   u = (atan2(b.y, b.x) − π) / (−2π),  v = (acos(b.z) − π) / (−π),  v = 0 the bottom row.
    // A LightFuse direction (X, Y, Z) is Blender (X, −Z, Y); our row coordinate is t = 1 − v.
    let cycles = |d: DVec3| {
        let b = DVec3::new(d.x, -d.z, d.y).normalize();
        let u = (b.y.atan2(b.x) - PI) / (-2.0 * PI);
        let v = (b.z.acos() - PI) / (-PI);
        [u, 1.0 - v]
    };
    // +X: atan2(0, 1) = 0 → u = ½; b.z = 0 → v = ½: the image centre.
    // +Y (up, Blender +Z): v = 1 → t = 0, the top row.
    // +Z (Blender −Y): atan2(−1, 0) = −π/2 → u = ¾.   −Z (Blender +Y): u = ¼.
    for (d, want) in [
        (Vec3::X, [0.5, 0.5]),
        (Vec3::Y, [0.5, 0.0]),
        (Vec3::Z, [0.75, 0.5]),
        (-Vec3::Z, [0.25, 0.5]),
        (Vec3::new(0.0, -1.0, 0.0), [0.5, 1.0]),
    ] {
        let got = envmap::direction_to_uv(d);
        let c = cycles(d.as_dvec3());
        for k in 0..2 {
            assert!((got[k] - want[k]).abs() < 1e-6, "{d}: {got:?} vs {want:?}");
            assert!(
                (got[k] as f64 - c[k]).abs() < 1e-6,
                "{d}: {got:?} vs Cycles {c:?}"
            );
        }
    }
    let mut rng = Pcg64::seed_from_u64(5);
    for _ in 0..1000 {
        let d = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        if d.length() < 0.1 {
            continue;
        }
        let got = envmap::direction_to_uv(d.as_vec3());
        let c = cycles(d);
        assert!((got[1] as f64 - c[1]).abs() < 1e-5);
        let du = (got[0] as f64 - c[0]).abs();
        assert!(
            du < 1e-5 || (du - 1.0).abs() < 1e-5,
            "{d}: {got:?} vs {c:?}"
        );
    }
    // Texel level: a map whose texels are their own indices, read at texel centres.
    let (w, h) = (16usize, 8usize);
    let env = Environment::new(
        "idx",
        w,
        h,
        (0..w * h).map(|i| [i as f32, 0.0, 0.0]).collect(),
    );
    let map = EnvMap::new(&env, 0.0);
    for (x, y) in [(0usize, 0usize), (3, 2), (8, 4), (12, 7), (15, 5)] {
        let d = envmap::uv_to_direction([(x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32]);
        let v = map.eval(d)[0];
        assert!(
            (v - (y * w + x) as f32).abs() < 1e-3,
            "texel ({x}, {y}): {v}"
        );
    }
    // +Z sits on the boundary between columns 11 and 12 of 16 (u = ¾ → x = 11.5 in centre
    // units), in the middle of rows 3 and 4: the bilinear mean of the four.
    let v = map.eval(Vec3::Z)[0];
    let want = (3 * 16 + 11 + 3 * 16 + 12 + 4 * 16 + 11 + 4 * 16 + 12) as f32 / 4.0;
    assert!((v - want).abs() < 1e-3, "{v} vs {want}");
}

fn random_env(w: usize, h: usize, seed: u64) -> Environment {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut px: Vec<[f32; 3]> = (0..w * h)
        .map(|_| {
            if rng.random::<f32>() < 0.2 {
                [0.0; 3] // black texels: only bilinear bleed lights them
            } else {
                let l = (rng.random_range(-3.0f32..2.0)).exp();
                [l, l * rng.random::<f32>(), l * rng.random::<f32>()]
            }
        })
        .collect();
    px[(h / 4) * w + w / 3] = [500.0, 450.0, 400.0]; // a sun
    Environment::new("random", w, h, px)
}

fn real_env() -> Environment {
    let dir = common::bundled_hdri_dir();
    let env = lightfuse::io::exr::read_environment(&dir.join("courtyard.exr"), "courtyard")
        .expect("Blender's courtyard.exr decodes");
    env.resample(64, 32)
}

/// ∫ pdf dω on a grid aligned with the texels (`sub` x `sub` points per texel).
fn env_pdf_integral(map: &EnvMap, sub: usize) -> f64 {
    let (w, h) = (map.width() * sub, map.height() * sub);
    let mut sum = 0.0;
    for y in 0..h {
        let t0 = PI * y as f64 / h as f64;
        let t1 = PI * (y + 1) as f64 / h as f64;
        let omega = 2.0 * PI / w as f64 * (t0.cos() - t1.cos());
        for x in 0..w {
            let uv = [(x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32];
            // Directions in map space; undo the rotation to get world directions.
            let d = envmap::uv_to_direction(uv);
            let r = (map.rotation_deg() as f64).to_radians();
            let (c, s) = (r.cos() as f32, r.sin() as f32);
            let world = Vec3::new(c * d.x - s * d.z, d.y, s * d.x + c * d.z);
            sum += map.pdf(world) as f64 * omega;
        }
    }
    sum
}

fn check_env_sampler(env: &Environment, rotation: f32, seed: u64) {
    let map = EnvMap::new(env, rotation);
    let integral = env_pdf_integral(&map, 4);
    assert!((integral - 1.0).abs() < 1e-4, "∫pdf = {integral}");
    // Samples: eval/pdf consistency and a (θ, φ) histogram over world directions (the grid is
    // not aligned with the texels: 12 x 24 cells, θ from +Y, φ = atan2(Z, X)).
    let n_samples = if cfg!(debug_assertions) {
        80_000
    } else {
        500_000
    };
    let (nt, np) = (12usize, 24usize);
    let mut observed = vec![0.0f64; nt * np];
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut unbiased_sum = [0.0f64; 3];
    for _ in 0..n_samples {
        let s = map.sample([rng.random(), rng.random()]);
        assert!((s.dir.length() - 1.0).abs() < 1e-5);
        assert_eq!(s.radiance, map.eval(s.dir));
        assert_eq!(s.pdf, map.pdf(s.dir));
        assert!(s.pdf > 0.0);
        for (acc, l) in unbiased_sum.iter_mut().zip(s.radiance) {
            *acc += l as f64 / s.pdf as f64;
        }
        let theta = (s.dir.y as f64).clamp(-1.0, 1.0).acos();
        let phi = (s.dir.z as f64).atan2(s.dir.x as f64).rem_euclid(2.0 * PI);
        let it = ((theta / PI * nt as f64) as usize).min(nt - 1);
        let ip = ((phi / (2.0 * PI) * np as f64) as usize).min(np - 1);
        observed[it * np + ip] += 1.0;
    }
    let sub = 24;
    let mut expected = vec![0.0f64; nt * np];
    for it in 0..nt {
        for ip in 0..np {
            let mut acc = 0.0;
            for a in 0..sub {
                let th = PI * (it as f64 + (a as f64 + 0.5) / sub as f64) / nt as f64;
                for b in 0..sub {
                    let ph = 2.0 * PI * (ip as f64 + (b as f64 + 0.5) / sub as f64) / np as f64;
                    let d = DVec3::new(th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin());
                    acc += map.pdf(d.as_vec3()) as f64 * th.sin();
                }
            }
            let cell = (PI / nt as f64) * (2.0 * PI / np as f64);
            expected[it * np + ip] = acc / (sub * sub) as f64 * cell * n_samples as f64;
        }
    }
    let (p, stat, dof) = chi_square(&observed, &expected);
    // ∫ L dω two ways: the texel sum (of the bilinear map: texels' solid-angle sum) and
    // the importance-sampled estimate.
    let exact = env.integral();
    let est = unbiased_sum.map(|v| v / n_samples as f64);
    println!(
        "env {} rot {rotation}: ∫pdf = {integral:.6}, chi² {stat:.1} dof {dof} p {p:.3e}; \
         ∫L dω {exact:.4?} vs IS estimate {est:.4?}",
        env.name
    );
    assert!(
        p > 1e-3,
        "{}: chi-square p = {p} (stat {stat}, dof {dof})",
        env.name
    );
    for c in 0..3 {
        assert!(
            rel_close(est[c], exact[c], 0.03, 1e-6),
            "{} ch {c}: IS {} vs texel sum {}",
            env.name,
            est[c],
            exact[c]
        );
    }
}

#[test]
fn env_sampler_random_map() {
    check_env_sampler(&random_env(48, 24, 3), 0.0, 31);
    check_env_sampler(&random_env(32, 16, 4), 37.5, 32);
}

#[test]
fn env_sampler_real_map() {
    check_env_sampler(&real_env(), 120.0, 33);
}

#[test]
fn env_rotation_by_90_degrees_is_a_roll_by_a_quarter_width() {
    let env = random_env(64, 32, 9);
    let (w, h) = (env.width, env.height);
    // rolled[:, c] = env[:, c − W/4]  (np.roll(env, +W/4, axis=1))
    let rolled = Environment::new(
        "rolled",
        w,
        h,
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                env.pixels[y * w + (x + w - w / 4) % w]
            })
            .collect(),
    );
    let turned = EnvMap::new(&env, 90.0);
    let plain = EnvMap::new(&rolled, 0.0);
    let unturned = EnvMap::new(&env, 0.0);
    let mut rng = Pcg64::seed_from_u64(10);
    let (mut differs, mut turned_matters) = (0, 0);
    for _ in 0..2000 {
        let d = Vec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        let (a, b) = (turned.eval(d), plain.eval(d));
        for c in 0..3 {
            assert!(
                rel_close(a[c] as f64, b[c] as f64, 1e-3, 1e-4),
                "{d}: {a:?} vs {b:?}"
            );
        }
        let pa = turned.pdf(d);
        let pb = plain.pdf(d);
        // The pdf is per texel: equal except within rounding of a texel border.
        if !rel_close(pa as f64, pb as f64, 1e-4, 0.0) {
            differs += 1;
        }
        if (unturned.eval(d)[0] - a[0]).abs() > 1e-3 {
            turned_matters += 1;
        }
    }
    assert!(differs <= 2, "{differs} pdfs differ");
    assert!(turned_matters > 1000, "the rotation changes the lookup");
    // The sign: +X reads column u = ¼ (−Z's column) after +90°.
    let [u, t] = turned.uv(Vec3::X);
    assert!((u - 0.25).abs() < 1e-6 && (t - 0.5).abs() < 1e-6, "{u} {t}");
}

// ------------------------------------------------------------------------ Sobol

#[test]
fn sobol_first_2k_samples_are_stratified() {
    for (pixel, seed) in [(0u32, 0u32), (17, 3), (123_456, 99)] {
        let s = Sampler::new(pixel, seed);
        for k in [4u32, 8, 10] {
            let n = 1u32 << k;
            for dim in [0u32, 1, 2, 5, 7] {
                let mut seen = vec![false; n as usize];
                for i in 0..n {
                    let cell = (s.get(i, dim) * n as f32) as usize;
                    assert!(
                        !seen[cell],
                        "pixel {pixel} dim {dim} 2^{k}: cell {cell} twice"
                    );
                    seen[cell] = true;
                }
            }
            // Dims 0 and 1 jointly: every elementary interval of shape 2^-a x 2^-(k-a) once.
            for a in 0..=k {
                let (nx, ny) = (1usize << a, 1usize << (k - a));
                let mut seen = vec![false; nx * ny];
                for i in 0..n {
                    let [x, y] = s.get_2d(i, 0);
                    let c = ((x * nx as f32) as usize) * ny + (y * ny as f32) as usize;
                    assert!(!seen[c], "pixel {pixel} 2^{k} interval {nx}x{ny}: twice");
                    seen[c] = true;
                }
            }
        }
    }
}

#[test]
fn sobol_replays_exactly_and_pixels_decorrelate() {
    let a = Sampler::new(42, 7);
    let a_again = Sampler::new(42, 7);
    // Replay in a different order gives identical bits.
    let forward: Vec<u32> = (0..256).map(|i| a.get(i, i % 9).to_bits()).collect();
    let backward: Vec<u32> = (0..256)
        .rev()
        .map(|i| a_again.get(i, i % 9).to_bits())
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .collect();
    assert_eq!(forward, backward);
    // Neighbouring pixels, and the same pixel under another seed: sample-wise correlation ~ 0.
    let n = 4096;
    for (p, q) in [
        (Sampler::new(42, 7), Sampler::new(43, 7)),
        (Sampler::new(42, 7), Sampler::new(42, 8)),
        (Sampler::new(0, 0), Sampler::new(1, 0)),
    ] {
        for dim in [0u32, 1, 4] {
            let xs: Vec<f64> = (0..n).map(|i| p.get(i, dim) as f64 - 0.5).collect();
            let ys: Vec<f64> = (0..n).map(|i| q.get(i, dim) as f64 - 0.5).collect();
            let cov: f64 = xs.iter().zip(&ys).map(|(x, y)| x * y).sum::<f64>() / n as f64;
            let corr = cov * 12.0; // variance of U(0,1) is 1/12
                                   // 4 standard errors of a correlation of n independent pairs.
            assert!(
                corr.abs() < 4.0 / (n as f64).sqrt(),
                "dim {dim}: corr {corr}"
            );
            let same = xs.iter().zip(&ys).filter(|(x, y)| x == y).count();
            assert!(same < 8, "{same} identical values");
        }
    }
}
