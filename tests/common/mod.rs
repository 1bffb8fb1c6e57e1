//! Helpers shared by integration tests.

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
