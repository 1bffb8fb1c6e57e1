//! Environment maps: Blender's bundled HDRIs (DWAB-compressed EXR) decode, resample keeping
//! energy, and survive `lightfuse env` and the glTF round trip.

use lightfuse::io::exr;
mod common;

use std::path::PathBuf;
use std::process::Command;

fn bundled_hdris() -> Vec<PathBuf> {
    let dir = common::bundled_hdri_dir();
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "exr"))
        .collect();
    files.sort();
    files
}

#[test]
fn blenders_dwab_hdris_decode_and_resample_keeping_energy() {
    let files = bundled_hdris();
    assert_eq!(files.len(), 8, "{files:?}");
    for f in &files {
        let env = exr::read_environment(f, "hdri").unwrap();
        assert_eq!(
            env.width,
            2 * env.height,
            "{}: lat-long maps are 2:1",
            f.display()
        );
        let mean: f64 = env.pixels.iter().flatten().map(|&v| v as f64).sum::<f64>()
            / (3 * env.pixels.len()) as f64;
        assert!(
            mean > 1e-3 && mean < 1e3,
            "{}: implausible mean radiance {mean}",
            f.display()
        );
        let small = env.resample(256, 128);
        let (a, b) = (env.integral(), small.integral());
        for c in 0..3 {
            assert!(
                (a[c] - b[c]).abs() <= 1e-4 * a[c],
                "{}: channel {c} {} vs {}",
                f.display(),
                a[c],
                b[c]
            );
        }
    }
}

#[test]
fn env_command_resamples_and_refuses_bad_sizes() {
    let f = &bundled_hdris()[0];
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("e.exr");
    let bin = env!("CARGO_BIN_EXE_lightfuse");
    let r = Command::new(bin)
        .args(["env"])
        .arg(f)
        .arg("-o")
        .arg(&out)
        .args(["--size", "64x32", "--json"])
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let env = exr::read_environment(&out, "e").unwrap();
    assert_eq!((env.width, env.height), (64, 32));
    let r = Command::new(bin)
        .args(["env"])
        .arg(f)
        .arg("-o")
        .arg(&out)
        .args(["--size", "0x32"])
        .output()
        .unwrap();
    assert_eq!(r.status.code(), Some(2));
}
