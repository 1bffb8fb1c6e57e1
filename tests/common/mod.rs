//! Fixtures shared by the integration tests: each test file that needs them declares
//! `mod common;` and uses its part.
#![allow(dead_code)] // each test crate uses some of these

pub mod inversion;
pub mod surfel_scenes;

use std::path::{Path, PathBuf};

/// Blender's 8 CC0 world HDRIs (DWAB EXR), shipped inside the bpy wheel of the project venv.
pub fn bundled_hdri_dir() -> PathBuf {
    let site = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/lib");
    std::fs::read_dir(&site)
        .unwrap_or_else(|_| {
            panic!(
                "{} is missing: run `bash scripts/setup.sh` (it installs bpy)",
                site.display()
            )
        })
        .filter_map(|e| e.ok())
        .map(|e| {
            e.path()
                .join("site-packages/bpy/5.0/datafiles/studiolights/world")
        })
        .find(|p| p.is_dir())
        .expect("bpy's studiolights/world folder in the venv")
}

/// Pushes a one-coefficient surfel whose base colour, metallic and roughness follow `color`, so
/// that a record's blended material says which surfels it blended (`tests/trace.rs`,
/// `tests/trace_backward.rs`).
pub fn push(
    s: &mut lightfuse::scene::Surfels,
    mu: [f32; 3],
    q: [f32; 4],
    scale: [f32; 2],
    alpha: f32,
    color: f32,
) {
    s.push(
        mu,
        q,
        scale,
        alpha,
        &[[0.0; 3]],
        [color, 1.0 - color, 0.5 * color],
        color,
        1.0 - color,
    );
}
