//! Deterministic random scenes for tests, benchmarks and fuzzing seeds: every attribute is
//! exercised with values that are valid but not round (so bit-exactness is really tested).

use super::{sh_coeffs, Component, EnvRef, Environment, Rigid, Scene, State, Surfels};

/// SplitMix64: tiny, fast and good enough to fill test data reproducibly.
pub struct SplitMix(pub u64);

impl SplitMix {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f32()
    }

    pub fn unit_quat(&mut self) -> [f32; 4] {
        let q = glam::Quat::from_xyzw(
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
            self.range(0.1, 1.0),
        );
        q.normalize().to_array()
    }
}

/// Random valid surfels.
pub fn random_surfels(rng: &mut SplitMix, n: usize, sh_degree: u8) -> Surfels {
    let mut s = Surfels::with_sh_degree(sh_degree);
    let k = sh_coeffs(sh_degree);
    let mut sh = vec![[0.0f32; 3]; k];
    for _ in 0..n {
        for c in sh.iter_mut() {
            *c = [
                rng.range(-2.0, 2.0),
                rng.range(-2.0, 2.0),
                rng.range(-2.0, 2.0),
            ];
        }
        s.push(
            [
                rng.range(-3.0, 3.0),
                rng.range(0.0, 2.5),
                rng.range(-3.0, 3.0),
            ],
            rng.unit_quat(),
            [rng.range(0.001, 0.05), rng.range(0.001, 0.05)],
            rng.range(0.0, 1.0),
            &sh,
            [rng.f32(), rng.f32(), rng.f32()],
            rng.f32(),
            rng.f32(),
        );
    }
    s
}

/// A scene with a background, `objects` objects, `states` states (each moving every object
/// and lit by its own small environment), `n` surfels per component.
pub fn random_scene(seed: u64, objects: usize, states: usize, n: usize, sh_degree: u8) -> Scene {
    let mut rng = SplitMix(seed);
    let mut components = vec![Component {
        name: super::BACKGROUND.into(),
        id: 0,
        surfels: random_surfels(&mut rng, n, sh_degree),
    }];
    for o in 0..objects {
        components.push(Component {
            name: format!("object{}", o + 1),
            id: o as u32 + 1,
            surfels: random_surfels(&mut rng, n, sh_degree),
        });
    }
    let mut environments = Vec::new();
    let mut st = Vec::new();
    for k in 0..states.max(1) {
        let (w, h) = (16, 8);
        let px = (0..w * h)
            .map(|_| {
                [
                    rng.range(0.0, 4.0),
                    rng.range(0.0, 4.0),
                    rng.range(0.0, 4.0),
                ]
            })
            .collect();
        environments.push(Environment::new(format!("env{k}"), w, h, px));
        let transforms = (0..=objects)
            .map(|o| {
                if o == 0 || k == 0 {
                    Rigid::IDENTITY
                } else {
                    Rigid {
                        rotation: rng.unit_quat(),
                        translation: [rng.range(-1.0, 1.0), 0.0, rng.range(-1.0, 1.0)],
                    }
                }
            })
            .collect();
        st.push(State {
            name: format!("state{k}"),
            transforms,
            environment: Some(EnvRef {
                index: k,
                rotation_deg: rng.range(0.0, 360.0),
            }),
        });
    }
    Scene {
        components,
        states: st,
        reference_state: 0,
        environments,
    }
}
