//! `.usda` round trips bit for bit, and bad input gives one clear error.

use lightfuse::io::usd::{read_usda, write_usda};
use lightfuse::scene::{sh_coeffs, Component, EnvRef, Environment, Rigid, Scene, State, Surfels};
use std::path::{Path, PathBuf};

/// SplitMix64: a tiny deterministic generator for test data.
struct Rng(u64);

impl Rng {
    fn u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1), with all 24 mantissa bits random-ish (not round decimals).
    fn unit(&mut self) -> f32 {
        (self.u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }
    /// Any finite f32 bit pattern (SH coefficients are unconstrained).
    fn any_finite(&mut self) -> f32 {
        loop {
            let v = f32::from_bits(self.u64() as u32);
            if v.is_finite() {
                return v;
            }
        }
    }
    fn quat(&mut self) -> [f32; 4] {
        let q = [
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
            self.range(0.1, 1.0),
        ];
        let n = q.iter().map(|x| x * x).sum::<f32>().sqrt();
        q.map(|x| x / n)
    }
}

fn surfels(rng: &mut Rng, n: usize, degree: u8) -> Surfels {
    let mut s = Surfels::with_sh_degree(degree);
    let k = sh_coeffs(degree);
    for i in 0..n {
        let sh: Vec<[f32; 3]> = (0..k)
            .map(|j| {
                if (i + j) % 7 == 0 {
                    [rng.any_finite(), rng.any_finite(), rng.any_finite()]
                } else {
                    [
                        rng.range(-2.0, 2.0),
                        rng.range(-1e-3, 1e-3),
                        rng.range(-50.0, 50.0),
                    ]
                }
            })
            .collect();
        s.push(
            [
                rng.range(-3.0, 3.0),
                rng.range(0.0, 2.5),
                rng.range(-3e4, 3e4),
            ],
            rng.quat(),
            [rng.range(1e-4, 0.05), rng.range(1e-30, 1e-20)],
            rng.unit(),
            &sh,
            [rng.unit(), rng.unit(), rng.unit()],
            rng.unit(),
            rng.unit(),
        );
    }
    if n >= 3 {
        // Edge values that text formats get wrong: signed zero, subnormals, exact bounds.
        s.position[0] = [-0.0, 1e-45, f32::MIN_POSITIVE];
        s.opacity[0] = 0.0;
        s.opacity[1] = 1.0;
        s.metallic[2] = 1.0;
        s.roughness[2] = 0.0;
        s.base_color[1] = [0.0, 1.0, 1e-40];
        s.sh[0] = [-0.0, f32::MAX, -f32::MAX];
        s.scale[2] = [f32::MIN_POSITIVE, 3.4e38];
    }
    s
}

fn env(rng: &mut Rng, name: &str, w: usize, h: usize) -> Environment {
    let px = (0..w * h)
        .map(|_| [rng.range(0.0, 4.0), rng.range(0.0, 1e4), rng.unit() * 1e-6])
        .collect();
    Environment::new(name, w, h, px)
}

fn rigid(rng: &mut Rng) -> Rigid {
    Rigid {
        rotation: rng.quat(),
        translation: [
            rng.range(-2.0, 2.0),
            rng.range(-1e-3, 1e-3),
            rng.range(-9.0, 9.0),
        ],
    }
}

/// Background + 2 objects, 4 states (3 lit by environments, one shared, one unlit), one
/// environment no state uses, awkward names.
fn test_scene(seed: u64, degrees: [u8; 3], n: usize) -> Scene {
    let mut rng = Rng(seed);
    let names = ["background", "chair \"7\" \\ ü", "EnvironmentLight"];
    let components: Vec<Component> = names
        .iter()
        .zip(degrees)
        .enumerate()
        .map(|(i, (name, d))| Component {
            name: name.to_string(),
            id: [0, 3, 9][i],
            surfels: surfels(&mut rng, n + i, d),
        })
        .collect();
    let mut states = Vec::new();
    let state_names = ["state0", "state 1", "state_1", "relit"];
    let envs = [Some(0), Some(1), Some(0), None];
    for (k, name) in state_names.iter().enumerate() {
        let mut transforms = vec![Rigid::IDENTITY];
        for _ in 1..components.len() {
            transforms.push(if k == 0 {
                Rigid::IDENTITY
            } else {
                rigid(&mut rng)
            });
        }
        states.push(State {
            name: name.to_string(),
            transforms,
            environment: envs[k].map(|index| EnvRef {
                index,
                rotation_deg: rng.range(-360.0, 360.0),
            }),
        });
    }
    let environments = vec![
        env(&mut rng, "state0", 16, 8),
        env(&mut rng, "state 1", 8, 4),
        env(&mut rng, "forest/../x", 4, 2),
    ];
    let scene = Scene {
        components,
        states,
        reference_state: 1,
        environments,
    };
    scene.validate(Path::new("test")).unwrap();
    scene
}

fn assert_bitwise_eq(a: &Scene, b: &Scene) {
    // PartialEq on f32 treats -0.0 == 0.0; compare bits too.
    assert_eq!(a, b);
    let bits = |s: &Scene| -> Vec<u32> {
        let mut v = Vec::new();
        for c in &s.components {
            let x = &c.surfels;
            v.extend(x.position.iter().flatten().map(|f| f.to_bits()));
            v.extend(x.rotation.iter().flatten().map(|f| f.to_bits()));
            v.extend(x.scale.iter().flatten().map(|f| f.to_bits()));
            v.extend(x.opacity.iter().map(|f| f.to_bits()));
            v.extend(x.sh.iter().flatten().map(|f| f.to_bits()));
            v.extend(x.base_color.iter().flatten().map(|f| f.to_bits()));
            v.extend(x.metallic.iter().map(|f| f.to_bits()));
            v.extend(x.roughness.iter().map(|f| f.to_bits()));
        }
        for st in &s.states {
            for t in &st.transforms {
                v.extend(t.rotation.iter().chain(&t.translation).map(|f| f.to_bits()));
            }
            if let Some(e) = st.environment {
                v.push(e.rotation_deg.to_bits());
            }
        }
        for e in &s.environments {
            v.extend(e.pixels.iter().flatten().map(|f| f.to_bits()));
        }
        v
    };
    assert!(bits(a) == bits(b), "bit patterns differ");
}

fn write_and_read(scene: &Scene) -> (tempfile::TempDir, PathBuf, Scene) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scene.usda");
    write_usda(scene, &path).unwrap();
    let back = read_usda(&path).unwrap();
    (dir, path, back)
}

#[test]
fn round_trip_sh_degree_3_is_bit_exact() {
    let scene = test_scene(7, [3, 3, 3], 300);
    let (dir, _, back) = write_and_read(&scene);
    assert_bitwise_eq(&scene, &back);
    // Environments are EXR files next to the layer.
    assert!(dir.path().join("scene.env/state0.exr").is_file());
    assert!(dir.path().join("scene.env/state_1.exr").is_file());
    assert!(dir.path().join("scene.env/forest_.._x.exr").is_file());
    // No temporary files are left behind.
    let leftovers: Vec<_> = walk(dir.path())
        .into_iter()
        .filter(|p| p.to_string_lossy().ends_with(".tmp"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn round_trip_sh_degree_0_and_mixed_degrees() {
    for degrees in [[0, 0, 0], [3, 1, 2]] {
        let scene = test_scene(11, degrees, 50);
        let (_dir, _, back) = write_and_read(&scene);
        assert_bitwise_eq(&scene, &back);
    }
}

#[test]
fn round_trip_empty_components_and_no_environments() {
    let mut scene = test_scene(3, [2, 2, 2], 0);
    for s in &mut scene.states {
        s.environment = None;
    }
    scene.environments.clear();
    scene.reference_state = 0;
    let (_dir, _, back) = write_and_read(&scene);
    assert_bitwise_eq(&scene, &back);
}

#[test]
fn rewriting_replaces_the_file() {
    let a = test_scene(1, [1, 1, 1], 10);
    let b = test_scene(2, [0, 0, 0], 5);
    let (_dir, path, _) = write_and_read(&a);
    write_usda(&b, &path).unwrap();
    assert_bitwise_eq(&b, &read_usda(&path).unwrap());
}

#[test]
fn layout_is_what_usd_expects() {
    let scene = test_scene(5, [3, 0, 1], 4);
    let (_dir, path, _) = write_and_read(&scene);
    let text = std::fs::read_to_string(&path).unwrap();
    for needle in [
        "upAxis = \"Y\"",
        "metersPerUnit = 1",
        "def ParticleField \"surfels\"",
        "\"ParticleFieldKernelGaussianSurfletAPI\"",
        "\"LightFuseSurfelMaterialAPI\"",
        "point3f[] positions = [",
        "quatf[] orientations = [",
        "float3[] scales = [",
        "float[] opacities = [",
        "uniform int radiance:sphericalHarmonicsDegree = 3",
        "float3[] radiance:sphericalHarmonicsCoefficients = [",
        "color3f[] lightfuse:baseColors = [",
        "variantSet \"state\" = {",
        "string state = \"state_1\"",
        "def DomeLight \"EnvironmentLight\"",
        "token inputs:texture:format = \"latlong\"",
        "@./scene.env/state0.exr@",
    ] {
        assert!(text.contains(needle), "missing {needle:?}");
    }
    // The object named "EnvironmentLight" does not collide with the DomeLight.
    assert!(text.contains("def Xform \"EnvironmentLight_2\""));
    // Quaternions are written (w, x, y, z).
    let q = scene.components[0].surfels.rotation[0];
    let start = text.find("quatf[] orientations = [(").unwrap() + "quatf[] orientations = [(".len();
    let first: Vec<f32> = text[start..text[start..].find(')').unwrap() + start]
        .split(", ")
        .map(|x| x.parse().unwrap())
        .collect();
    assert_eq!(first, vec![q[3], q[0], q[1], q[2]]);
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Bad input
// ---------------------------------------------------------------------------------------------

/// Writes a small scene, applies `edit` to the text, reads it back and returns the error.
fn error_after(edit: impl FnOnce(String) -> String) -> String {
    let scene = test_scene(9, [1, 1, 1], 6);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.usda");
    write_usda(&scene, &path).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, edit(text)).unwrap();
    let err = read_usda(&path).unwrap_err();
    assert!(err.is_user_error(), "{err}");
    let msg = err.to_string();
    assert!(
        msg.contains("bad.usda"),
        "error does not name the file: {msg}"
    );
    msg
}

/// Replaces the value of the first attribute declared as `decl` with `value`.
fn set_attr(text: &str, decl: &str, value: &str) -> String {
    let start = text
        .find(decl)
        .unwrap_or_else(|| panic!("{decl} not in file"));
    let eq = start + text[start..].find(" = ").unwrap() + 3;
    let end = eq + text[eq..].find('\n').unwrap();
    format!("{}{}{}", &text[..eq], value, &text[end..])
}

#[test]
fn missing_file_is_an_io_error_naming_it() {
    let err = read_usda(Path::new("/nonexistent/scene.usda")).unwrap_err();
    assert!(err.is_user_error());
    assert!(err.to_string().contains("/nonexistent/scene.usda"));
}

#[test]
fn truncated_file_is_a_clear_error() {
    let msg = error_after(|t| t[..t.len() * 2 / 3].to_string());
    assert!(msg.contains("USD text"), "{msg}");
    let msg = error_after(|t| t[..t.len() - 3].to_string());
    assert!(msg.contains("USD text"), "{msg}");
}

#[test]
fn missing_attribute_names_prim_and_attribute() {
    let msg = error_after(|t| {
        let start = t.find("            float[] opacities").unwrap();
        let end = start + t[start..].find('\n').unwrap() + 1;
        format!("{}{}", &t[..start], &t[end..])
    });
    assert!(
        msg.contains("</Scene/background/surfels>.opacities"),
        "{msg}"
    );
    assert!(msg.contains("missing attribute"), "{msg}");

    let msg =
        error_after(|t| t.replacen("float3 xformOp:translate", "float3 xformOp:translateX", 1));
    assert!(msg.contains("xformOp:translate"), "{msg}");
    assert!(msg.contains("{state=state0}"), "{msg}");
}

#[test]
fn count_mismatch_says_what_was_expected() {
    let msg = error_after(|t| set_attr(&t, "float[] lightfuse:metallics", "[0.5, 0.25]"));
    assert!(msg.contains("lightfuse:metallics"), "{msg}");
    assert!(msg.contains("expected 6 elements"), "{msg}");
    assert!(msg.contains("found 2"), "{msg}");

    let msg = error_after(|t| {
        set_attr(
            &t,
            "float3[] radiance:sphericalHarmonicsCoefficients",
            "[(1, 2, 3)]",
        )
    });
    assert!(
        msg.contains("radiance:sphericalHarmonicsCoefficients"),
        "{msg}"
    );
    assert!(msg.contains("expected 24 elements"), "{msg}");
}

#[test]
fn nan_and_out_of_range_values_are_refused() {
    let msg = error_after(|t| set_attr(&t, "float[] opacities", "[nan, 0.5, 0.5, 0.5, 0.5, 0.5]"));
    assert!(msg.contains("opacity"), "{msg}");
    let msg = error_after(|t| set_attr(&t, "float[] opacities", "[2, 0.5, 0.5, 0.5, 0.5, 0.5]"));
    assert!(msg.contains("opacity") && msg.contains("[0, 1]"), "{msg}");
    let msg = error_after(|t| set_attr(&t, "uniform int radiance:sphericalHarmonicsDegree", "4"));
    assert!(msg.contains("sphericalHarmonicsDegree"), "{msg}");
}

#[test]
fn wrong_types_and_metadata_are_refused() {
    let msg = error_after(|t| t.replacen("float[] opacities", "double[] opacities", 1));
    assert!(msg.contains("expected a float[] value"), "{msg}");
    let msg = error_after(|t| t.replacen("upAxis = \"Y\"", "upAxis = \"Z\"", 1));
    assert!(msg.contains("upAxis"), "{msg}");
    let msg = error_after(|t| t.replacen("metersPerUnit = 1", "metersPerUnit = 0.01", 1));
    assert!(msg.contains("metersPerUnit"), "{msg}");
    let msg = error_after(|t| {
        t.replacen(
            "\"ParticleFieldKernelGaussianSurfletAPI\", ",
            "\"ParticleFieldKernelGaussianEllipsoidAPI\", ",
            1,
        )
    });
    assert!(
        msg.contains("ParticleFieldKernelGaussianSurfletAPI"),
        "{msg}"
    );
}

#[test]
fn missing_environment_file_names_it() {
    let scene = test_scene(9, [0, 0, 0], 3);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.usda");
    write_usda(&scene, &path).unwrap();
    std::fs::remove_file(dir.path().join("s.env/state0.exr")).unwrap();
    let err = read_usda(&path).unwrap_err();
    assert!(err.is_user_error());
    assert!(err.to_string().contains("state0.exr"), "{err}");
}

#[test]
fn invalid_scene_is_not_written() {
    let mut scene = test_scene(4, [0, 0, 0], 3);
    scene.components[1].surfels.opacity[0] = f32::NAN;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("x.usda");
    assert!(write_usda(&scene, &path).is_err());
    assert!(!path.exists());
}
