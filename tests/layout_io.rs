//! layout.json read and write, layouts taken from scenes, and the errors a user sees.

use lightfuse::io::layout::{read_layout, write_layout};
use lightfuse::scene::synthetic::random_scene;
use lightfuse::scene::{Layout, Rigid};
use std::path::Path;

#[test]
fn layout_json_round_trips_and_applies_to_a_scene() {
    let dir = tempfile::tempdir().unwrap();
    let scene = random_scene(2, 2, 2, 10, 0);
    let mut layout = Layout::default();
    let t = Rigid {
        rotation: glam::Quat::from_rotation_y(0.5).to_array(),
        translation: [0.25, 0.0, -1.0],
    };
    layout.objects.insert("object2".into(), t);
    let p = dir.path().join("layout.json");
    write_layout(&layout, &p).unwrap();
    let back = read_layout(&p).unwrap();
    let b = back.objects["object2"];
    assert!(b.quat().angle_between(t.quat()) < 1e-6 && b.translation == t.translation);
    let state = scene.state_from_layout("edited", &back, &p).unwrap();
    assert!(state.transforms[1].is_identity() && !state.transforms[2].is_identity());

    // A scene is a layout too: its reference state's placement.
    let g = dir.path().join("s.glb");
    lightfuse::io::write_scene(&scene, &g).unwrap();
    assert_eq!(read_layout(&g).unwrap().objects.len(), 2);
}

fn write(dir: &Path, text: &str) -> std::path::PathBuf {
    let p = dir.join("bad.json");
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn layout_errors_name_the_file_and_the_object() {
    let dir = tempfile::tempdir().unwrap();
    let scale = r#"{"format":"lightfuse-layout/1","objects":{"chair":[[2,0,0,0],[0,2,0,0],[0,0,2,0],[0,0,0,1]]}}"#;
    let e = read_layout(&write(dir.path(), scale))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("bad.json") && e.contains("objects.chair") && e.contains("scale"),
        "{e}"
    );
    let shear = r#"{"format":"lightfuse-layout/1","objects":{"chair":[[1,0.5,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}"#;
    let e = read_layout(&write(dir.path(), shear))
        .unwrap_err()
        .to_string();
    assert!(e.contains("objects.chair"), "{e}");
    let e = read_layout(&write(dir.path(), r#"{"format":"other","objects":{}}"#))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("format") && e.contains("lightfuse-layout/1"),
        "{e}"
    );
    let e = read_layout(&write(
        dir.path(),
        r#"{"format":"lightfuse-layout/1","objects":{"chair":[[1,0,0]]}}"#,
    ))
    .unwrap_err()
    .to_string();
    assert!(e.contains("4x4"), "{e}");

    let scene = random_scene(2, 1, 1, 5, 0);
    let mut layout = Layout::default();
    layout.objects.insert("sofa".into(), Rigid::IDENTITY);
    let e = scene
        .state_from_layout("x", &layout, Path::new("layout.json"))
        .unwrap_err();
    assert!(
        e.is_user_error()
            && e.to_string().contains("objects.sofa")
            && e.to_string().contains("object1"),
        "{e}"
    );
    layout.objects.clear();
    layout.objects.insert("background".into(), Rigid::IDENTITY);
    assert!(
        scene
            .state_from_layout("x", &layout, Path::new("layout.json"))
            .is_err(),
        "the background never moves"
    );
}

#[test]
fn dataset_errors_are_clear() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("dataset.json");
    std::fs::write(&p, r#"{"format":"nerfstudio","objects":[],"states":[]}"#).unwrap();
    let e = lightfuse::io::dataset::Dataset::read(dir.path())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("dataset.json") && e.contains("lightfuse-dataset/1"),
        "{e}"
    );
    std::fs::write(&p, r#"{"format":"lightfuse-dataset/1","up":"+Y","objects":[{"id":1,"name":"a"}],"states":[{"name":"s","split":"train","object_poses":{"b":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}]}"#).unwrap();
    let e = lightfuse::io::dataset::Dataset::read(&p)
        .unwrap_err()
        .to_string();
    assert!(e.contains("object_poses.b"), "{e}");
    std::fs::write(&p, r#"{"format":"lightfuse-dataset/1","up":"+Y","objects":[],"states":[{"name":"s","split":"train","frames":[{"file_path":"x.exr","transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],"fl_x":0,"fl_y":10,"cx":1,"cy":1,"w":2,"h":2}]}]}"#).unwrap();
    let e = lightfuse::io::dataset::Dataset::read(&p)
        .unwrap_err()
        .to_string();
    assert!(e.contains("frames[0].fl_x") && e.contains("focal"), "{e}");
}
