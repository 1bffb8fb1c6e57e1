//! Our files checked by tools no one here wrote: the Khronos glTF-Validator, and Babylon.js's
//! KHR_gaussian_splatting loader (headless, NullEngine). Both come from `tools/` (npm, pinned,
//! installed by `scripts/setup.sh`); these tests fail, not skip, when they are missing.

use lightfuse::io;
use lightfuse::scene::synthetic::random_scene;
use lightfuse::scene::SH_C0;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn tools() -> PathBuf {
    let t = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools");
    assert!(
        t.join("node_modules").join("gltf-validator").is_dir(),
        "tools/node_modules is missing: run `bash scripts/setup.sh` (npm ci in tools/)"
    );
    t
}

fn node(script: &str, args: &[&Path], extra: &[&str]) -> (bool, String) {
    let out = Command::new("node")
        .arg(tools().join(script))
        .args(args)
        .args(extra)
        .output()
        .expect("node is installed");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr),
    )
}

/// The only errors glTF-Validator 2.0.0-dev.3.10 raises on our files: it predates
/// KHR_gaussian_splatting, whose attribute names contain ':'. They are downgraded to warnings,
/// and each one must name an attribute in this list, so nothing else can hide behind it.
const KNOWN_SPLAT_ATTRIBUTE_PREFIXES: [&str; 2] =
    ["KHR_gaussian_splatting:", "LIGHTFUSE_gaussian_surfels:"];
const DOWNGRADED: &str = "MESH_PRIMITIVE_INVALID_ATTRIBUTE";

fn validate(path: &Path) {
    let (ok, out) = node(
        "validate_gltf.mjs",
        &[path],
        &["--override", &format!("{DOWNGRADED}=1")],
    );
    let report: Value =
        serde_json::from_str(&out[out.find('{').expect("JSON report")..]).expect("report is JSON");
    let issues = &report["issues"];
    assert!(
        ok && issues["numErrors"] == 0,
        "{}: validator errors: {out}",
        path.display()
    );
    for m in issues["messages"].as_array().unwrap() {
        let code = m["code"].as_str().unwrap();
        if m["severity"].as_u64().unwrap() > 1 {
            continue; // infos and hints: unused buffer views of environments, unknown extensions
        }
        assert_eq!(code, DOWNGRADED, "unexpected warning: {m}");
        let pointer = m["pointer"].as_str().unwrap();
        let attr = pointer.rsplit('/').next().unwrap();
        assert!(
            KNOWN_SPLAT_ATTRIBUTE_PREFIXES
                .iter()
                .any(|p| attr.starts_with(p)),
            "downgraded error on a non-splat attribute: {m}"
        );
    }
    // Sanity: the downgrade really happened (the validator does check our attributes).
    let n = issues["messages"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|m| m["code"] == DOWNGRADED)
        .count();
    assert!(
        n > 0,
        "expected the validator to flag the splat attribute names"
    );
}

#[test]
fn gltf_validator_reports_no_errors() {
    let dir = tempfile::tempdir().unwrap();
    let scene = random_scene(11, 2, 3, 64, 3);
    for name in ["s.glb", "s.gltf"] {
        let p = dir.path().join(name);
        io::write_scene(&scene, &p).unwrap();
        validate(&p);
    }
}

fn clamp255(v: f32) -> u8 {
    // Babylon's encoder: (value + 0.5) | 0, clamped.
    if v <= 0.0 {
        0
    } else if v >= 255.0 {
        255
    } else {
        (v + 0.5) as u8
    }
}

#[test]
fn babylon_reads_our_values() {
    let dir = tempfile::tempdir().unwrap();
    let scene = random_scene(5, 2, 2, 150, 1);
    let p = dir.path().join("b.glb");
    io::write_scene(&scene, &p).unwrap();
    let (ok, out) = node("babylon_read.mjs", &[&p], &[]);
    assert!(ok, "{out}");
    let line = out
        .lines()
        .find(|l| l.starts_with("{\"meshes\""))
        .unwrap_or_else(|| panic!("no JSON from Babylon: {out}"));
    let v: Value = serde_json::from_str(line).unwrap();
    let meshes = v["meshes"].as_array().unwrap();
    assert_eq!(meshes.len(), scene.components.len());
    for (m, c) in meshes.iter().zip(&scene.components) {
        let s = &c.surfels;
        assert_eq!(m["count"].as_u64().unwrap() as usize, s.len());
        let f = |k: &str| -> Vec<f32> {
            m[k].as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap() as f32)
                .collect()
        };
        let u = |k: &str| -> Vec<u8> {
            m[k].as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap() as u8)
                .collect()
        };
        let (pos, scale, rgba, quat) = (f("position"), f("scale"), u("rgba"), u("quat_wxyz"));
        for i in 0..s.len() {
            // Float32 values pass through Babylon exactly.
            assert_eq!(
                &pos[3 * i..3 * i + 3],
                &s.position[i],
                "{} surfel {i} position",
                c.name
            );
            assert_eq!(
                &scale[3 * i..3 * i + 3],
                &[s.scale[i][0], s.scale[i][1], 0.0],
                "{} surfel {i} scale",
                c.name
            );
            // 8-bit encodings: recompute them from our values (±1 for f32 vs f64 rounding).
            let sh0 = s.sh_of(i)[0];
            let want = [
                clamp255((0.5 + SH_C0 * sh0[0]) * 255.0),
                clamp255((0.5 + SH_C0 * sh0[1]) * 255.0),
                clamp255((0.5 + SH_C0 * sh0[2]) * 255.0),
                clamp255(s.opacity[i] * 255.0),
            ];
            let q = s.rotation[i];
            let want_q = [q[3], q[0], q[1], q[2]].map(|x| clamp255(x * 127.5 + 127.5));
            for k in 0..4 {
                assert!(
                    (rgba[4 * i + k] as i32 - want[k] as i32).abs() <= 1,
                    "{} surfel {i} rgba[{k}]: {} vs {}",
                    c.name,
                    rgba[4 * i + k],
                    want[k]
                );
                assert!(
                    (quat[4 * i + k] as i32 - want_q[k] as i32).abs() <= 1,
                    "{} surfel {i} quat[{k}]",
                    c.name
                );
            }
        }
    }
}
