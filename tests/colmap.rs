//! The COLMAP reader and camera models against files and projections from real COLMAP
//! (pycolmap 4.2.1, `tests/data/colmap/make_fixtures.py`).

use lightfuse::io::colmap::lens::{Lens, LensModel};
use lightfuse::io::colmap::{read_model, Model};
use std::path::{Path, PathBuf};

fn data(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/colmap")
        .join(rel)
}

fn json(rel: &str) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(data(rel)).unwrap()).unwrap()
}

fn f64s(v: &serde_json::Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// Every model's projection equals COLMAP's to 1e-9 px (both are the same closed forms in
/// doubles; what is left is rounding), and unprojecting the pixel gives the ray back to 1e-8
/// (Newton's stopping tolerance is 1e-9 px).
#[test]
fn every_camera_model_projects_as_colmap_does() {
    let fx = json("lens.json");
    let points: Vec<Vec<f64>> = fx["camera_points"]
        .as_array()
        .unwrap()
        .iter()
        .map(f64s)
        .collect();
    let mut checked = 0;
    for m in fx["models"].as_array().unwrap() {
        let name = m["model"].as_str().unwrap();
        let model = LensModel::from_name(name).unwrap_or_else(|| panic!("{name} unknown"));
        assert_eq!(
            LensModel::from_id(m["model_id"].as_i64().unwrap() as i32),
            Some(model)
        );
        let lens = Lens {
            model,
            width: 64,
            height: 48,
            params: f64s(&m["params"]),
        };
        assert_eq!(lens.params.len(), model.num_params(), "{name}");
        if m["pixels"].is_null() {
            assert!(lens.unsupported().is_some(), "{name} is refused");
            continue;
        }
        assert!(lens.unsupported().is_none(), "{name}");
        for (p, want) in points.iter().zip(m["pixels"].as_array().unwrap()) {
            let want = f64s(want);
            let got = lens
                .project([p[0], p[1], p[2]])
                .unwrap_or_else(|| panic!("{name} {p:?}"));
            let err = (got[0] - want[0]).hypot(got[1] - want[1]);
            assert!(err < 1e-9, "{name}: {p:?} -> {got:?}, COLMAP {want:?}");
            let q = lens
                .unproject(got)
                .unwrap_or_else(|| panic!("{name} unproject {got:?}"));
            let back = (q[0] - p[0] / p[2]).hypot(q[1] - p[1] / p[2]);
            assert!(back < 1e-8, "{name}: unproject {got:?} = {q:?}, ray {p:?}");
        }
        checked += 1;
    }
    assert_eq!(checked, 17, "every model but EQUIRECTANGULAR");
}

/// The pinhole image of a distorted camera sees only what the photo recorded: every pixel
/// of its border maps inside the photo, and one side touches the photo's border (the zoom is
/// the least that does this).
#[test]
fn the_pinhole_image_stays_inside_the_photo() {
    let fx = json("lens.json");
    for m in fx["models"].as_array().unwrap() {
        let model = LensModel::from_name(m["model"].as_str().unwrap()).unwrap();
        let lens = Lens {
            model,
            width: 64,
            height: 48,
            params: f64s(&m["params"]),
        };
        if lens.unsupported().is_some() {
            continue;
        }
        let pin = lens.pinhole().unwrap();
        let mut touch = f64::INFINITY;
        for i in 0..=200 {
            let t = i as f64 / 200.0;
            for px in [
                [0.0, t * 48.0],
                [64.0, t * 48.0],
                [t * 64.0, 0.0],
                [t * 64.0, 48.0],
            ] {
                let s = lens.source_pixel(&pin, px).unwrap();
                let inside = s[0].min(64.0 - s[0]).min(s[1]).min(48.0 - s[1]);
                assert!(inside > -1e-3, "{}: {px:?} -> {s:?}", model.name());
                touch = touch.min(inside);
            }
        }
        if !lens.is_pinhole() {
            assert!(
                touch < 0.05,
                "{}: zoom not least ({touch} px to spare)",
                model.name()
            );
        }
    }
}

fn truth_check(model: &Model) {
    let t = json("model_truth.json");
    assert_eq!(model.images.len(), t["images"].as_object().unwrap().len());
    for im in model.images.values() {
        let ti = &t["images"][&im.name];
        assert_eq!(ti["image_id"].as_u64().unwrap() as u32, im.id);
        assert_eq!(ti["camera_id"].as_u64().unwrap() as u32, im.camera_id);
        assert_eq!(
            ti["num_points2D"].as_u64().unwrap() as usize,
            im.points2d.len()
        );
        let m = im.cam_from_world();
        for (r, row) in ti["cam_from_world"].as_array().unwrap().iter().enumerate() {
            for (c, v) in f64s(row).iter().enumerate() {
                assert!((m[r][c] - v).abs() < 1e-12, "{} [{r}][{c}]", im.name);
            }
        }
    }
    assert_eq!(model.points.len(), t["points"].as_object().unwrap().len());
    for p in &model.points {
        let tp = &t["points"][p.id.to_string()];
        // serde_json's default float parser may be one ulp off; the readers themselves are
        // compared bit for bit below (binary against text).
        for (a, b) in f64s(&tp["xyz"]).iter().zip(p.xyz) {
            assert!((a - b).abs() < 1e-12, "point {}", p.id);
        }
        assert_eq!(tp["track_length"].as_u64().unwrap() as usize, p.track.len());
        assert!((tp["error"].as_f64().unwrap() - p.error).abs() < 1e-12);
    }
    for (id, c) in &model.cameras {
        let tc = &t["cameras"][id.to_string()];
        assert_eq!(tc["model"].as_str().unwrap(), c.model.name());
        assert_eq!(f64s(&tc["params"]), c.params);
        assert_eq!(tc["width"].as_u64().unwrap() as u32, c.width);
    }
}

#[test]
fn binary_and_text_models_read_as_colmap_wrote_them() {
    let bin = read_model(&data("model_bin")).unwrap();
    let txt = read_model(&data("model_txt")).unwrap();
    truth_check(&bin);
    truth_check(&txt);
    assert_eq!(bin.cameras, txt.cameras);
    // Text keeps 17 significant digits: the same doubles.
    assert_eq!(bin.images, txt.images);
    assert_eq!(bin.points, txt.points);
}

fn copy_model(kind: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for e in std::fs::read_dir(data(&format!("model_{kind}"))).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), dir.path().join(e.file_name())).unwrap();
    }
    dir
}

fn error_of(dir: &Path) -> String {
    let e = read_model(dir).expect_err("must be refused");
    assert!(e.is_user_error(), "{e}");
    e.to_string()
}

/// Every truncation of every binary file is one error naming the file, never a panic.
#[test]
fn truncated_binary_files_are_refused_naming_the_file() {
    for part in ["cameras", "images", "points3D"] {
        let full = std::fs::read(data(&format!("model_bin/{part}.bin"))).unwrap();
        for cut in (0..full.len()).step_by(7) {
            let dir = copy_model("bin");
            std::fs::write(dir.path().join(format!("{part}.bin")), &full[..cut]).unwrap();
            let msg = error_of(dir.path());
            assert!(msg.contains(&format!("{part}.bin")), "{cut}: {msg}");
        }
    }
}

#[test]
fn inconsistent_models_are_refused_naming_the_field() {
    // An image whose camera is not in cameras.txt.
    let dir = copy_model("txt");
    let cams = std::fs::read_to_string(dir.path().join("cameras.txt")).unwrap();
    let cams: String = cams
        .lines()
        .filter(|l| !l.starts_with("3 "))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(dir.path().join("cameras.txt"), cams).unwrap();
    let msg = error_of(dir.path());
    assert!(
        msg.contains("cameras.txt") || msg.contains("images.txt"),
        "{msg}"
    );
    assert!(msg.contains("camera 3"), "{msg}");

    // A camera with too few parameters, and an unknown model.
    let dir = copy_model("txt");
    let p = dir.path().join("cameras.txt");
    let c = std::fs::read_to_string(&p).unwrap().replace(
        "OPENCV 64 48 72 69 31.5 24.5 -0.11 0.02 0.002",
        "OPENCV 64 48 72 69 31.5",
    );
    std::fs::write(&p, c.replace("-0.001\n", "\n")).unwrap();
    let msg = error_of(dir.path());
    assert!(
        msg.contains("camera 2.params") && msg.contains("expected 8 parameters for OPENCV"),
        "{msg}"
    );
    let dir = copy_model("txt");
    let p = dir.path().join("cameras.txt");
    let c = std::fs::read_to_string(&p)
        .unwrap()
        .replace("PINHOLE 64", "PINHOL 64");
    std::fs::write(&p, c).unwrap();
    let msg = error_of(dir.path());
    assert!(msg.contains("unknown camera model PINHOL"), "{msg}");

    // A track naming a keypoint the image does not have.
    let dir = copy_model("txt");
    let p = dir.path().join("points3D.txt");
    let c = std::fs::read_to_string(&p)
        .unwrap()
        .replacen(" 1 0 2 0", " 1 99 2 0", 1);
    std::fs::write(&p, c).unwrap();
    let msg = error_of(dir.path());
    assert!(
        msg.contains("points3D.txt") && msg.contains("keypoint 99 of image 1"),
        "{msg}"
    );

    // A folder of numbered models: COLMAP split the capture.
    let dir = tempfile::tempdir().unwrap();
    for k in ["0", "1"] {
        let sub = dir.path().join(k);
        std::fs::create_dir(&sub).unwrap();
        std::fs::copy(data("model_bin/cameras.bin"), sub.join("cameras.bin")).unwrap();
    }
    let msg = error_of(dir.path());
    assert!(msg.contains("holds 2 (0, 1)"), "{msg}");
}
