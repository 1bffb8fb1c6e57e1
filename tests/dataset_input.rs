//! What training reads of a dataset, and every way that input can be wrong (issue 5, "Bad
//! input"): each error names the file and the field and says what was expected.

use lightfuse::error::Error;
use lightfuse::io::dataset::Dataset;
use lightfuse::io::exr::{write_channels, Channels};
use serde_json::{json, Value};
use std::path::Path;

const W: u32 = 4;
const H: u32 = 3;

fn exr(path: &Path, names: &[&str], w: u32, h: u32, value: impl Fn(usize, usize) -> f32) {
    let n = (w * h) as usize;
    let channels = names
        .iter()
        .enumerate()
        .map(|(c, name)| (name.to_string(), (0..n).map(|i| value(i, c)).collect()))
        .collect();
    write_channels(
        &Channels {
            width: w as usize,
            height: h as usize,
            channels,
        },
        path,
    )
    .unwrap();
}

fn png(path: &Path, w: u32, h: u32, ids: &[u8]) {
    image::GrayImage::from_raw(w, h, ids.to_vec())
        .unwrap()
        .save(path)
        .unwrap();
}

/// A one-state, one-view dataset whose mask shows object 1 at pixel 5.
fn dataset(dir: &Path) -> Value {
    exr(&dir.join("rgb.exr"), &["R", "G", "B"], W, H, |i, c| {
        0.1 * c as f32 + 0.01 * i as f32
    });
    exr(&dir.join("depth.exr"), &["Z"], W, H, |i, _| 1.0 + i as f32);
    exr(&dir.join("normal.exr"), &["R", "G", "B"], W, H, |_, c| {
        if c == 2 {
            1.0
        } else {
            0.0
        }
    });
    let mut ids = vec![0u8; (W * H) as usize];
    ids[5] = 1;
    png(&dir.join("mask.png"), W, H, &ids);
    json!({
        "format": "lightfuse-dataset/1",
        "up": "+Y",
        "objects": [{"id": 1, "name": "cup"}],
        "states": [{
            "name": "state0", "split": "train",
            "frames": [{
                "file_path": "rgb.exr", "depth_file_path": "depth.exr",
                "normal_file_path": "normal.exr", "mask_path": "mask.png",
                "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],
                "fl_x": 4.0, "fl_y": 4.0, "cx": 2.0, "cy": 1.5, "w": W, "h": H
            }]
        }]
    })
}

fn read(dir: &Path, v: &Value) -> Result<Vec<Vec<lightfuse::io::dataset::Observation>>, Error> {
    let p = dir.join("dataset.json");
    std::fs::write(&p, serde_json::to_vec_pretty(v).unwrap()).unwrap();
    Dataset::read(&p)?.training_observations()
}

/// Asserts a user error (exit code 2) whose message holds every `needle`.
fn fails(dir: &Path, v: &Value, needles: &[&str]) {
    let e = read(dir, v).expect_err("bad input must be refused");
    assert!(e.is_user_error(), "{e}");
    let msg = e.to_string();
    for n in needles {
        assert!(msg.contains(n), "{msg:?} should mention {n:?}");
    }
}

#[test]
fn a_good_dataset_loads_every_pass() {
    let dir = tempfile::tempdir().unwrap();
    let v = dataset(dir.path());
    let obs = read(dir.path(), &v).unwrap();
    assert_eq!((obs.len(), obs[0].len()), (1, 1));
    let o = &obs[0][0];
    assert_eq!(o.rgb.len(), 12);
    assert_eq!(o.rgb[3], [0.03, 0.13, 0.23]);
    assert_eq!(o.depth[7], 8.0);
    assert_eq!(o.normal[0], [0.0, 0.0, 1.0]);
    assert_eq!(o.mask[5], 1);
    assert_eq!(o.mask.iter().filter(|&&m| m == 0).count(), 11);
}

#[test]
fn broken_json_and_header_fields_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let v = dataset(dir.path());
    let mut bad = v.clone();
    bad["states"][0]["frames"][0]["w"] = json!("four");
    fails(dir.path(), &bad, &["dataset.json"]);
    let mut bad = v.clone();
    bad.as_object_mut().unwrap().remove("states");
    fails(dir.path(), &bad, &["dataset.json", "states"]);
    let mut bad = v.clone();
    bad["up"] = json!("+Z");
    fails(dir.path(), &bad, &["dataset.json", "up", "+Y"]);
    let mut bad = v.clone();
    bad["objects"] = json!([{"id": 1, "name": "cup"}, {"id": 1, "name": "mug"}]);
    fails(dir.path(), &bad, &["objects[1]", "unique"]);
    let mut bad = v.clone();
    bad["objects"][0]["id"] = json!(0);
    fails(dir.path(), &bad, &["objects[0].id"]);
    let mut bad = v.clone();
    bad["states"][0]["split"] = json!("test");
    fails(dir.path(), &bad, &["split", "train"]);
    // Symmetry axes of one object must meet at one point (pose errors are measured there).
    let mut ok = v.clone();
    ok["objects"][0]["symmetries"] = json!([
        {"axis": [0, 1, 0], "order": 0, "offset": [0, 0.07, 0]},
        {"axis": [1, 0, 0], "order": 0, "offset": [0, 0.07, 0]}
    ]);
    read(dir.path(), &ok).expect("a ball's two axes through its centre");
    let mut bad = ok.clone();
    bad["objects"][0]["symmetries"][1]["offset"] = json!([0, 0.05, 0]);
    fails(
        dir.path(),
        &bad,
        &["objects[0].symmetries[1].offset", "one point"],
    );
}

#[test]
fn missing_or_mis_sized_images_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let v = dataset(dir.path());
    let mut bad = v.clone();
    bad["states"][0]["frames"][0]["normal_file_path"] = json!("nowhere.exr");
    fails(dir.path(), &bad, &["nowhere.exr"]);
    let mut bad = v.clone();
    bad["states"][0]["frames"][0]
        .as_object_mut()
        .unwrap()
        .remove("depth_file_path");
    fails(dir.path(), &bad, &["states[0].frames[0].depth_file_path"]);
    exr(&dir.path().join("small.exr"), &["Z"], 3, 3, |_, _| 1.0);
    let mut bad = v.clone();
    bad["states"][0]["frames"][0]["depth_file_path"] = json!("small.exr");
    fails(dir.path(), &bad, &["small.exr", "size", "4x3", "3x3"]);
    png(&dir.path().join("wide.png"), 5, 3, &[1; 15]);
    let mut bad = v.clone();
    bad["states"][0]["frames"][0]["mask_path"] = json!("wide.png");
    fails(dir.path(), &bad, &["wide.png", "size"]);
    exr(&dir.path().join("nan.exr"), &["Z"], W, H, |i, _| {
        if i == 2 {
            f32::NAN
        } else {
            1.0
        }
    });
    let mut bad = v.clone();
    bad["states"][0]["frames"][0]["depth_file_path"] = json!("nan.exr");
    fails(dir.path(), &bad, &["nan.exr", "Z", "pixel 2"]);
}

#[test]
fn masks_frames_and_objects_must_agree() {
    let dir = tempfile::tempdir().unwrap();
    let v = dataset(dir.path());
    let mut ids = vec![0u8; 12];
    ids[1] = 7;
    png(&dir.path().join("stranger.png"), W, H, &ids);
    let mut bad = v.clone();
    bad["states"][0]["frames"][0]["mask_path"] = json!("stranger.png");
    fails(dir.path(), &bad, &["stranger.png", "object id 7"]);

    let mut bad = v.clone();
    bad["states"][0]["frames"] = json!([]);
    fails(dir.path(), &bad, &["states[0].frames", "state0"]);

    png(&dir.path().join("empty.png"), W, H, &[0; 12]);
    let mut bad = v.clone();
    bad["states"][0]["frames"][0]["mask_path"] = json!("empty.png");
    fails(dir.path(), &bad, &["objects", "cup", "no training view"]);
}

/// Ground truth for evaluation (never training): the albedo pass, the state's environment and
/// the objects' recorded materials.
#[test]
fn ground_truth_albedo_environment_and_materials_read_for_evaluation() {
    let dir = tempfile::tempdir().unwrap();
    let mut v = dataset(dir.path());
    exr(
        &dir.path().join("albedo.exr"),
        &["R", "G", "B"],
        W,
        H,
        |i, c| {
            if i == 5 {
                [0.8, 0.4, 0.1][c]
            } else {
                0.0
            }
        },
    );
    let env = lightfuse::scene::Environment::new(
        "x",
        4,
        2,
        (0..8).map(|i| [i as f32, -1.0, 0.5]).collect(),
    );
    std::fs::create_dir(dir.path().join("env")).unwrap();
    lightfuse::io::exr::write_environment(&env, &dir.path().join("env/state0.exr")).unwrap();
    v["states"][0]["frames"][0]["albedo_file_path"] = json!("albedo.exr");
    v["states"][0]["environment"] = json!("env/state0.exr");
    v["states"][0]["environment_source"] =
        json!({"name": "sky", "rotation_deg": 90.0, "scale": 2.0});
    v["objects"][0]["material"] = json!({"metallic": 1.0, "roughness": 0.25});
    let p = dir.path().join("dataset.json");
    std::fs::write(&p, serde_json::to_vec_pretty(&v).unwrap()).unwrap();
    let d = Dataset::read(&p).unwrap();

    let albedo = d
        .albedo(0, 0)
        .unwrap()
        .expect("the frame names an albedo pass");
    assert_eq!(albedo.len(), 12);
    assert_eq!(albedo[5], [0.8, 0.4, 0.1]);
    assert_eq!(albedo[0], [0.0; 3]);
    let e = d
        .environment(0)
        .unwrap()
        .expect("the state names its environment");
    assert_eq!((e.name.as_str(), e.width, e.height), ("state0", 4, 2));
    assert_eq!(e.pixels[3], [3.0, 0.0, 0.5], "negative texels are set to 0");
    let src = d.states[0].environment_source.as_ref().unwrap();
    assert_eq!(src.rotation_deg, Some(90.0));
    let m = d.objects[0].material.unwrap();
    assert_eq!((m.metallic, m.roughness), (1.0, 0.25));

    // Old datasets: no albedo, no environment, no material.
    let plain = dataset(dir.path());
    std::fs::write(&p, serde_json::to_vec_pretty(&plain).unwrap()).unwrap();
    let d = Dataset::read(&p).unwrap();
    assert!(d.albedo(0, 0).unwrap().is_none());
    assert!(d.environment(0).unwrap().is_none());
    assert!(d.objects[0].material.is_none());

    // A named but missing albedo pass, or one of the wrong size, is a user error naming it.
    let mut bad = v.clone();
    bad["states"][0]["frames"][0]["albedo_file_path"] = json!("gone/albedo.exr");
    std::fs::write(&p, serde_json::to_vec_pretty(&bad).unwrap()).unwrap();
    let e = Dataset::read(&p).unwrap().albedo(0, 0).unwrap_err();
    assert!(
        e.is_user_error() && e.to_string().contains("gone/albedo.exr"),
        "{e}"
    );
    exr(
        &dir.path().join("small.exr"),
        &["R", "G", "B"],
        2,
        2,
        |_, _| 0.5,
    );
    bad["states"][0]["frames"][0]["albedo_file_path"] = json!("small.exr");
    std::fs::write(&p, serde_json::to_vec_pretty(&bad).unwrap()).unwrap();
    let e = Dataset::read(&p).unwrap().albedo(0, 0).unwrap_err();
    assert!(
        e.to_string().contains("small.exr") && e.to_string().contains("size"),
        "{e}"
    );
    let mut bad = v.clone();
    bad["states"][0]["environment"] = json!("env/nowhere.exr");
    std::fs::write(&p, serde_json::to_vec_pretty(&bad).unwrap()).unwrap();
    let e = Dataset::read(&p).unwrap().environment(0).unwrap_err();
    assert!(
        e.is_user_error() && e.to_string().contains("nowhere.exr"),
        "{e}"
    );
    let mut bad = v.clone();
    bad["objects"][0]["material"]["roughness"] = json!(1.5);
    fails(
        dir.path(),
        &bad,
        &["objects[0].material.roughness", "[0, 1]"],
    );
}
