//! Writes a deterministic random scene for tests of other tools (usd-core, Blender, the fuzzer's
//! seeds); names with dots, mixed SH degrees, moved objects, environments per state:
//! `cargo run --release --example write_test_scene -- <out.usda|out.glb> [surfels per component]`.
//! Beside it, `<out>.expected.json` lists what a reader must find: names, prim paths, variants,
//! and the first surfels' values as f32 bit patterns (exact to compare, no decimal rounding).

use lightfuse::scene::synthetic::{random_surfels as surfels, SplitMix as Rng};
use lightfuse::scene::{Component, EnvRef, Environment, Rigid, Scene, State};
use serde_json::{json, Value};
use std::path::PathBuf;

fn scene(n: usize) -> Scene {
    let mut rng = Rng(20_240_601);
    let components = vec![
        Component {
            name: "background".into(),
            id: 0,
            surfels: surfels(&mut rng, n, 3),
        },
        Component {
            name: "chair".into(),
            id: 1,
            surfels: surfels(&mut rng, n / 2 + 1, 3),
        },
        Component {
            name: "vase.001".into(),
            id: 2,
            surfels: surfels(&mut rng, n / 3 + 1, 0),
        },
    ];
    let states = (0..3)
        .map(|k| State {
            name: format!("state{k}"),
            transforms: (0..3)
                .map(|i| {
                    if i == 0 || k == 0 {
                        Rigid::IDENTITY
                    } else {
                        Rigid {
                            rotation: rng.unit_quat(),
                            translation: [rng.range(-1.0, 1.0), 0.0, rng.range(-1.0, 1.0)],
                        }
                    }
                })
                .collect(),
            environment: Some(EnvRef {
                index: k,
                rotation_deg: rng.range(0.0, 360.0),
            }),
        })
        .collect();
    let environments = (0..3)
        .map(|k| {
            let (w, h) = (32, 16);
            let px = (0..w * h)
                .map(|_| {
                    [
                        rng.range(0.0, 2.0),
                        rng.range(0.0, 2.0),
                        rng.range(0.0, 2.0),
                    ]
                })
                .collect();
            Environment::new(format!("state{k}"), w, h, px)
        })
        .collect();
    Scene {
        components,
        states,
        reference_state: 0,
        environments,
    }
}

fn bits<const N: usize>(v: &[[f32; N]]) -> Value {
    json!(v
        .iter()
        .map(|e| e.map(f32::to_bits).to_vec())
        .collect::<Vec<_>>())
}

fn main() {
    let mut args = std::env::args().skip(1);
    let Some(out) = args.next().map(PathBuf::from) else {
        eprintln!("usage: write_test_scene <out.usda|out.glb> [surfels per component]");
        std::process::exit(2);
    };
    let n: usize = args
        .next()
        .map_or(200, |s| s.parse().expect("a surfel count"));
    let scene = scene(n);
    if let Err(e) = lightfuse::io::write_scene(&scene, &out) {
        eprintln!("{e}");
        std::process::exit(2);
    }
    const FIRST: usize = 5;
    let components: Vec<Value> = scene
        .components
        .iter()
        .map(|c| {
            let s = &c.surfels;
            let k = FIRST.min(s.len());
            json!({
                "name": c.name, "id": c.id, "count": s.len(), "sh_degree": s.sh_degree,
                // Quaternions as USD writes them: (w, x, y, z).
                "orientations": bits(&s.rotation[..k].iter().map(|q| [q[3], q[0], q[1], q[2]]).collect::<Vec<_>>()),
                "positions": bits(&s.position[..k]),
                "scales": bits(&s.scale[..k].iter().map(|x| [x[0], x[1], 0.0]).collect::<Vec<_>>()),
                "opacities": bits(&s.opacity[..k].iter().map(|x| [*x]).collect::<Vec<_>>()),
                "sh": bits(&s.sh[..k * s.sh_stride()]),
                "base_colors": bits(&s.base_color[..k]),
                "metallics": bits(&s.metallic[..k].iter().map(|x| [*x]).collect::<Vec<_>>()),
                "roughnesses": bits(&s.roughness[..k].iter().map(|x| [*x]).collect::<Vec<_>>()),
            })
        })
        .collect();
    let states: Vec<Value> = scene
        .states
        .iter()
        .map(|s| {
            json!({
                "name": s.name,
                "translations": bits(&s.transforms.iter().map(|t| t.translation).collect::<Vec<_>>()),
                "orients": bits(&s.transforms.iter().map(|t| { let q = t.rotation; [q[3], q[0], q[1], q[2]] }).collect::<Vec<_>>()),
                "environment": s.environment.map(|e| json!({
                    "index": e.index,
                    "name": scene.environments[e.index].name,
                    "rotation_deg_bits": e.rotation_deg.to_bits(),
                    "dome_rotate_y_bits": lightfuse::io::usd::dome_rotate_y(e.rotation_deg).to_bits(),
                })),
            })
        })
        .collect();
    let expected = json!({
        "components": components,
        "states": states,
        "reference_state": scene.reference_state,
        "environments": scene.environments.iter().map(|e| &e.name).collect::<Vec<_>>(),
    });
    let mut side = out.clone().into_os_string();
    side.push(".expected.json");
    std::fs::write(&side, serde_json::to_string_pretty(&expected).unwrap())
        .expect("write the sidecar");
}
