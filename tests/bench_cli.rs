//! `lightfuse bench` refuses what it cannot compare, before rendering anything.

use std::process::Command;

#[test]
fn bench_bad_input_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("s.glb");
    lightfuse::io::write_scene(
        &lightfuse::scene::synthetic::random_scene(1, 1, 1, 10, 0),
        &scene,
    )
    .unwrap();
    let bin = env!("CARGO_BIN_EXE_lightfuse");
    let out = Command::new(bin)
        .arg("bench")
        .arg(&scene)
        .arg("--dataset")
        .arg(dir.path().join("nowhere"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("nowhere"));

    let ds = dir.path().join("dataset.json");
    std::fs::write(&ds, r#"{"format":"lightfuse-dataset/1","up":"+Y","objects":[],"states":[{"name":"a","split":"train","frames":[{"file_path":"x.exr","transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],"fl_x":10,"fl_y":10,"cx":1,"cy":1,"w":2,"h":2}]}]}"#).unwrap();
    let out = Command::new(bin)
        .arg("bench")
        .arg(&scene)
        .arg("--dataset")
        .arg(&ds)
        .args(["--state", "b"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("dataset.json") && err.contains("\"b\""),
        "{err}"
    );
    // The state exists but the dataset has no scene.blend for Cycles.
    let out = Command::new(bin)
        .arg("bench")
        .arg(&scene)
        .arg("--dataset")
        .arg(&ds)
        .args(["--state", "a"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("scene.blend"));
}
