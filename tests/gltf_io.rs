//! glTF reading and writing: bit-exact round trips, and one test per kind of bad input, each
//! checking the message names the file and the field, and that the CLI exits with code 2.

use lightfuse::io::{self, gltf};
use lightfuse::scene::synthetic::random_scene;
use lightfuse::scene::Scene;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn scene() -> Scene {
    random_scene(7, 2, 3, 200, 3)
}

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_lightfuse")
}

#[test]
fn glb_round_trip_is_bit_exact_for_every_sh_degree() {
    let dir = tempfile::tempdir().unwrap();
    for degree in 0..=3 {
        let s = random_scene(degree as u64, 2, 3, 57, degree);
        let path = dir.path().join(format!("d{degree}.glb"));
        io::write_scene(&s, &path).unwrap();
        let back = io::read_scene(&path).unwrap();
        assert_eq!(back, s, "degree {degree}");
    }
}

#[test]
fn glb_to_gltf_to_glb_preserves_every_byte() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene();
    let a = dir.path().join("a.glb");
    io::write_scene(&s, &a).unwrap();
    let out = Command::new(bin())
        .args(["convert"])
        .arg(&a)
        .arg(dir.path().join("b.gltf"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(dir.path().join("b.bin").is_file());
    assert!(dir.path().join("b.env").join("0_env0.exr").is_file());
    let mid = io::read_scene(&dir.path().join("b.gltf")).unwrap();
    assert_eq!(mid, s);
    let out = Command::new(bin())
        .args(["convert"])
        .arg(dir.path().join("b.gltf"))
        .arg(dir.path().join("c.glb"))
        .output()
        .unwrap();
    assert!(out.status.success());
    assert_eq!(
        std::fs::read(&a).unwrap(),
        std::fs::read(dir.path().join("c.glb")).unwrap()
    );
}

#[test]
fn empty_components_and_states_without_environment_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = random_scene(3, 2, 2, 10, 1);
    s.components[2].surfels = lightfuse::scene::Surfels::with_sh_degree(1);
    s.states[1].environment = None;
    let p = dir.path().join("e.glb");
    io::write_scene(&s, &p).unwrap();
    assert_eq!(io::read_scene(&p).unwrap(), s);
}

#[test]
fn ours_is_used_never_required() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("s.gltf");
    io::write_scene(&scene(), &p).unwrap();
    let v: Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    let used: Vec<&str> = v["extensionsUsed"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_str().unwrap())
        .collect();
    assert!(
        used.contains(&"KHR_gaussian_splatting") && used.contains(&"LIGHTFUSE_gaussian_surfels")
    );
    assert!(v.get("extensionsRequired").is_none());
    let prim = &v["meshes"][0]["primitives"][0];
    assert_eq!(prim["mode"], 0);
    assert_eq!(
        prim["extensions"]["KHR_gaussian_splatting"]["kernel"],
        "surfel"
    );
    // Flat: the third scale component is written as 0 for every surfel.
    let acc = prim["attributes"]["KHR_gaussian_splatting:SCALE"]
        .as_u64()
        .unwrap() as usize;
    assert_eq!(v["accessors"][acc]["type"], "VEC3");
}

#[test]
fn schemas_accept_what_we_write() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas");
    let load = |name: &str| -> Value {
        serde_json::from_slice(&std::fs::read(root.join(name)).unwrap()).unwrap()
    };
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("s.gltf");
    io::write_scene(&scene(), &p).unwrap();
    let v: Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    let checks = [
        (
            "glTF.LIGHTFUSE_gaussian_surfels.schema.json",
            v["extensions"]["LIGHTFUSE_gaussian_surfels"].clone(),
        ),
        (
            "primitive.LIGHTFUSE_gaussian_surfels.schema.json",
            v["meshes"][0]["primitives"][0]["extensions"]["KHR_gaussian_splatting"]["extensions"]
                ["LIGHTFUSE_gaussian_surfels"]
                .clone(),
        ),
        (
            "scene.LIGHTFUSE_gaussian_surfels.schema.json",
            v["scenes"][1]["extensions"]["LIGHTFUSE_gaussian_surfels"].clone(),
        ),
    ];
    for (schema, instance) in checks {
        let validator = jsonschema::validator_for(&load(schema)).unwrap();
        let errors: Vec<String> = validator
            .iter_errors(&instance)
            .map(|e| e.to_string())
            .collect();
        assert!(errors.is_empty(), "{schema}: {errors:?}");
        // The schema must be able to fail: a wrong type is refused.
        let mut broken = instance.clone();
        broken
            .as_object_mut()
            .unwrap()
            .insert("bogus".into(), Value::Bool(true));
        assert!(
            !validator.is_valid(&broken),
            "{schema} accepts unknown properties"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Bad input

/// Writes the test scene as `.gltf` + `.bin` and returns (gltf path, JSON, bin bytes).
fn gltf_parts(dir: &Path) -> (PathBuf, Value, Vec<u8>) {
    let p = dir.join("s.gltf");
    io::write_scene(&scene(), &p).unwrap();
    let v = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
    let b = std::fs::read(dir.join("s.bin")).unwrap();
    (p, v, b)
}

fn save(p: &Path, v: &Value, bin: &[u8]) {
    std::fs::write(p, serde_json::to_vec(v).unwrap()).unwrap();
    std::fs::write(p.with_extension("bin"), bin).unwrap();
}

/// Byte offset in the buffer of element `i`, component `k` of the accessor an attribute of
/// mesh 0 uses.
fn float_offset(v: &Value, attr: &str, i: usize, k: usize) -> usize {
    let acc = &v["accessors"][v["meshes"][0]["primitives"][0]["attributes"][attr]
        .as_u64()
        .unwrap() as usize];
    let view = &v["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
    let per = match acc["type"].as_str().unwrap() {
        "SCALAR" => 1,
        "VEC3" => 3,
        "VEC4" => 4,
        t => panic!("{t}"),
    };
    view["byteOffset"].as_u64().unwrap() as usize + 4 * (i * per + k)
}

fn set_float(v: &Value, bin: &mut [u8], attr: &str, i: usize, k: usize, x: f32) {
    let o = float_offset(v, attr, i, k);
    bin[o..o + 4].copy_from_slice(&x.to_le_bytes());
}

/// Asserts reading fails with a user error mentioning every needle, and that the CLI's
/// `info` exits with code 2 and prints the same message without panicking.
fn assert_bad(path: &Path, needles: &[&str]) {
    let err = io::read_scene(path).unwrap_err();
    let msg = err.to_string();
    assert!(err.is_user_error(), "not a user error: {msg}");
    assert!(
        msg.contains(&*path.file_name().unwrap().to_string_lossy()),
        "message does not name the file: {msg}"
    );
    for n in needles {
        assert!(msg.contains(n), "message lacks {n:?}: {msg}");
    }
    let out = Command::new(bin()).arg("info").arg(path).output().unwrap();
    assert_eq!(
        out.status.code(),
        Some(2),
        "exit code; stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.starts_with("error: ") && !stderr.contains("panicked"),
        "{stderr}"
    );
}

fn glb_bytes(dir: &Path) -> Vec<u8> {
    let p = dir.join("good.glb");
    io::write_scene(&scene(), &p).unwrap();
    std::fs::read(p).unwrap()
}

#[test]
fn truncated_glb() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = glb_bytes(dir.path());
    let p = dir.path().join("trunc.glb");
    for cut in [0, 7, 12, 19, 100, bytes.len() / 2, bytes.len() - 1] {
        std::fs::write(&p, &bytes[..cut]).unwrap();
        assert_bad(&p, &["GLB"]);
    }
}

#[test]
fn wrong_magic() {
    let dir = tempfile::tempdir().unwrap();
    let mut bytes = glb_bytes(dir.path());
    bytes[0..4].copy_from_slice(b"glTX");
    let p = dir.path().join("magic.glb");
    std::fs::write(&p, &bytes).unwrap();
    assert_bad(&p, &["magic", "glTF"]);
}

#[test]
fn wrong_chunk_length() {
    let dir = tempfile::tempdir().unwrap();
    let mut bytes = glb_bytes(dir.path());
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap());
    // BIN chunk header follows the JSON chunk; claim more bytes than the file has.
    let bin_at = 20 + json_len as usize;
    bytes[bin_at..bin_at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
    let p = dir.path().join("chunk.glb");
    std::fs::write(&p, &bytes).unwrap();
    assert_bad(&p, &["chunk 1 length"]);
    // And a JSON chunk longer than the file.
    let mut bytes = glb_bytes(dir.path());
    bytes[12..16].copy_from_slice(&(json_len + 1_000_000).to_le_bytes());
    std::fs::write(&p, &bytes).unwrap();
    assert_bad(&p, &["chunk 0 length"]);
}

#[test]
fn accessor_count_mismatch() {
    let dir = tempfile::tempdir().unwrap();
    let (p, mut v, b) = gltf_parts(dir.path());
    let acc = v["meshes"][0]["primitives"][0]["attributes"]["KHR_gaussian_splatting:OPACITY"]
        .as_u64()
        .unwrap() as usize;
    v["accessors"][acc]["count"] = 199.into();
    save(&p, &v, &b);
    assert_bad(&p, &["OPACITY", "count", "expected 200"]);
}

#[test]
fn accessor_type_mismatch() {
    let dir = tempfile::tempdir().unwrap();
    let (p, mut v, b) = gltf_parts(dir.path());
    let acc = v["meshes"][0]["primitives"][0]["attributes"]["KHR_gaussian_splatting:ROTATION"]
        .as_u64()
        .unwrap() as usize;
    v["accessors"][acc]["type"] = "VEC3".into();
    save(&p, &v, &b);
    assert_bad(&p, &["ROTATION", "type", "expected VEC4"]);
    let (p, mut v, b) = gltf_parts(dir.path());
    v["accessors"][acc]["componentType"] = 5123.into();
    save(&p, &v, &b);
    assert_bad(&p, &["componentType", "5126"]);
}

#[test]
fn buffer_out_of_range() {
    let dir = tempfile::tempdir().unwrap();
    let (p, mut v, b) = gltf_parts(dir.path());
    v["bufferViews"][3]["byteOffset"] = (b.len() as u64).into();
    save(&p, &v, &b);
    assert_bad(&p, &["bufferViews[3]", "out of buffer"]);
    // A bin file shorter than the declared buffer.
    let (p, v, b) = gltf_parts(dir.path());
    save(&p, &v, &b[..b.len() / 2]);
    assert_bad(&p, &["buffers[0].byteLength"]);
}

#[test]
fn non_finite_values() {
    let dir = tempfile::tempdir().unwrap();
    for (attr, k, x, field) in [
        ("POSITION", 1, f32::NAN, "position"),
        (
            "KHR_gaussian_splatting:SH_DEGREE_2_COEF_3",
            2,
            f32::INFINITY,
            "sh",
        ),
        (
            "LIGHTFUSE_gaussian_surfels:ROUGHNESS",
            0,
            f32::NEG_INFINITY,
            "roughness",
        ),
    ] {
        let (p, v, mut b) = gltf_parts(dir.path());
        set_float(&v, &mut b, attr, 17, k, x);
        save(&p, &v, &b);
        assert_bad(&p, &[field, "surfel 17", "finite"]);
    }
}

#[test]
fn negative_scale() {
    let dir = tempfile::tempdir().unwrap();
    let (p, v, mut b) = gltf_parts(dir.path());
    set_float(&v, &mut b, "KHR_gaussian_splatting:SCALE", 5, 1, -0.01);
    save(&p, &v, &b);
    assert_bad(&p, &["scale", "surfel 5", "positive"]);
}

#[test]
fn opacity_outside_unit_interval() {
    let dir = tempfile::tempdir().unwrap();
    for x in [1.5, -0.25] {
        let (p, v, mut b) = gltf_parts(dir.path());
        set_float(&v, &mut b, "KHR_gaussian_splatting:OPACITY", 9, 0, x);
        save(&p, &v, &b);
        assert_bad(&p, &["opacity", "surfel 9", "[0, 1]"]);
    }
}

#[test]
fn zero_quaternion() {
    let dir = tempfile::tempdir().unwrap();
    let (p, v, mut b) = gltf_parts(dir.path());
    for k in 0..4 {
        set_float(&v, &mut b, "KHR_gaussian_splatting:ROTATION", 3, k, 0.0);
    }
    save(&p, &v, &b);
    assert_bad(&p, &["rotation", "surfel 3", "zero"]);
}

#[test]
fn missing_kernel_or_color_space() {
    let dir = tempfile::tempdir().unwrap();
    for key in ["kernel", "colorSpace"] {
        let (p, mut v, b) = gltf_parts(dir.path());
        v["meshes"][1]["primitives"][0]["extensions"]["KHR_gaussian_splatting"]
            .as_object_mut()
            .unwrap()
            .remove(key);
        save(&p, &v, &b);
        assert_bad(&p, &[key, "meshes[1]"]);
    }
}

#[test]
fn unknown_required_extension() {
    let dir = tempfile::tempdir().unwrap();
    let (p, mut v, b) = gltf_parts(dir.path());
    v["extensionsRequired"] = serde_json::json!([
        "KHR_gaussian_splatting",
        "KHR_spz_gaussian_splats_compression"
    ]);
    save(&p, &v, &b);
    assert_bad(
        &p,
        &["extensionsRequired", "KHR_spz_gaussian_splats_compression"],
    );
}

#[test]
fn missing_environment_file() {
    let dir = tempfile::tempdir().unwrap();
    let (p, _, _) = gltf_parts(dir.path());
    std::fs::remove_file(dir.path().join("s.env").join("1_env1.exr")).unwrap();
    assert_bad(&p, &["environments[1].uri", "1_env1.exr", "missing"]);
}

#[test]
fn unsupported_exr_layout() {
    let dir = tempfile::tempdir().unwrap();
    let (p, _, _) = gltf_parts(dir.path());
    // A depth-only EXR where an RGB environment belongs.
    let img = lightfuse::io::exr::Channels {
        width: 4,
        height: 2,
        channels: vec![("Z".into(), vec![1.0; 8])],
    };
    lightfuse::io::exr::write_channels(&img, &dir.path().join("s.env").join("0_env0.exr")).unwrap();
    let err = io::read_scene(&p).unwrap_err().to_string();
    assert!(
        err.contains("0_env0.exr") && err.contains("R, G and B"),
        "{err}"
    );
    let out = Command::new(bin()).arg("info").arg(&p).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn bad_input_never_damages_an_existing_output() {
    let dir = tempfile::tempdir().unwrap();
    let out_path = dir.path().join("out.glb");
    io::write_scene(&scene(), &out_path).unwrap();
    let before = std::fs::read(&out_path).unwrap();
    let bad = dir.path().join("bad.glb");
    std::fs::write(&bad, b"glTF\x02\0\0\0garbage").unwrap();
    let out = Command::new(bin())
        .arg("convert")
        .arg(&bad)
        .arg(&out_path)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert_eq!(std::fs::read(&out_path).unwrap(), before);
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
        .collect();
    assert!(leftovers.is_empty());
}

#[test]
fn not_a_lightfuse_scene() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("plain.gltf");
    std::fs::write(
        &p,
        br#"{"asset":{"version":"2.0"},"scenes":[{"nodes":[]}]}"#,
    )
    .unwrap();
    assert_bad(&p, &["not a LightFuse scene"]);
    let p = dir.path().join("garbage.gltf");
    std::fs::write(&p, b"{ this is not json").unwrap();
    assert_bad(&p, &["JSON"]);
}

#[test]
fn reader_handles_strided_views_and_data_uris() {
    // Another writer may interleave attributes and embed the buffer as base64.
    let dir = tempfile::tempdir().unwrap();
    let (p, mut v, b) = gltf_parts(dir.path());
    use base64::Engine;
    v["buffers"][0]["uri"] = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&b)
    )
    .into();
    std::fs::write(&p, serde_json::to_vec(&v).unwrap()).unwrap();
    std::fs::remove_file(dir.path().join("s.bin")).unwrap();
    assert_eq!(io::read_scene(&p).unwrap(), scene());
    let _ = gltf::KHR;
}

#[test]
fn glb_to_usda_to_glb_preserves_every_byte() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.glb");
    io::write_scene(&scene(), &a).unwrap();
    for (from, to) in [("a.glb", "b.usda"), ("b.usda", "c.glb")] {
        let out = Command::new(bin())
            .arg("convert")
            .arg(dir.path().join(from))
            .arg(dir.path().join(to))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{from} -> {to}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    assert_eq!(io::read_scene(&dir.path().join("b.usda")).unwrap(), scene());
    assert_eq!(
        std::fs::read(&a).unwrap(),
        std::fs::read(dir.path().join("c.glb")).unwrap()
    );
}

#[test]
fn ply_export_has_the_3dgs_layout() {
    let dir = tempfile::tempdir().unwrap();
    let s = scene();
    let p = dir.path().join("s.ply");
    let out = Command::new(bin())
        .arg("convert")
        .arg(dir.path().join("missing.glb"))
        .arg(&p)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let g = dir.path().join("s.glb");
    io::write_scene(&s, &g).unwrap();
    let out = Command::new(bin())
        .arg("convert")
        .arg(&g)
        .arg(&p)
        .args(["--state", "state1"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let bytes = std::fs::read(&p).unwrap();
    let end = b"end_header\n";
    let h = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&bytes[..h]).unwrap();
    let props: Vec<&str> = header
        .lines()
        .filter_map(|l| l.strip_prefix("property float "))
        .collect();
    assert!(header.contains(&format!("element vertex {}", s.surfel_count())));
    assert_eq!(
        &props[..9],
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    );
    assert_eq!(
        props.iter().filter(|p| p.starts_with("f_rest_")).count(),
        45
    );
    assert_eq!(
        &props[props.len() - 8..],
        ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    );
    let floats: Vec<f32> = bytemuck::pod_collect_to_vec(&bytes[h..]);
    let row = props.len();
    assert_eq!(floats.len(), row * s.surfel_count());
    // Object 1's first surfel, placed as in state1: centre moved, log scale, logit opacity,
    // rotation (w, x, y, z), and the channel-major f_rest of the 3DGS reference code.
    let (c, t) = (&s.components[1].surfels, s.states[1].transforms[1]);
    let r = &floats[row * s.components[0].surfels.len()..][..row];
    let want_p = t.transform_point(c.position[0]);
    for k in 0..3 {
        assert!((r[k] - want_p[k]).abs() < 1e-6);
    }
    assert!((r[row - 7] - c.scale[0][0].ln()).abs() < 1e-6);
    let a = c.opacity[0];
    assert!((r[row - 8] - (a / (1.0 - a)).ln()).abs() < 1e-4);
    let q = t.transform_rotation(c.rotation[0]);
    assert!((r[row - 4] - q[3]).abs() < 1e-6 && (r[row - 3] - q[0]).abs() < 1e-6);
    assert_eq!(r[9], c.sh_of(0)[1][0]); // f_rest_0: red, coefficient 1
    assert_eq!(r[9 + 15], c.sh_of(0)[1][1]); // f_rest_15: green, coefficient 1
}
