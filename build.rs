//! With the `denoise` feature, embeds the Open Image Denoise library directory as the rpath of
//! everything this package links (the binary, tests, examples, benches), so they run without
//! `LD_LIBRARY_PATH`.
//!
//! The `oidn` crate's own build script links `libOpenImageDenoise` from `$OIDN_DIR/lib` (or,
//! without `OIDN_DIR`, from what pkg-config finds) but sets no runtime search path. We take the
//! same `OIDN_DIR` — scripts/setup.sh points it at the venv's pyoidn wheel — and add
//! `-Wl,-rpath,<absolute $OIDN_DIR/lib>`. The library's own dependencies (its core and CPU
//! device modules, TBB) sit beside it and are found through its `$ORIGIN` rpath. Without
//! `OIDN_DIR` a system install found by pkg-config is assumed to be on the loader's path.

use std::env;
use std::path::PathBuf;

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=OIDN_DIR");
    if env::var_os("CARGO_FEATURE_DENOISE").is_none() {
        return;
    }
    let Some(dir) = env::var_os("OIDN_DIR").filter(|d| !d.is_empty()) else {
        println!(
            "cargo:warning=the denoise feature without OIDN_DIR: linking whatever Open Image \
             Denoise pkg-config finds, with no rpath (scripts/setup.sh sets OIDN_DIR to the \
             venv's pyoidn)"
        );
        return;
    };
    let lib = PathBuf::from(dir).join("lib");
    // Relative paths would be resolved against the binary's working directory at run time.
    let lib = lib.canonicalize().unwrap_or_else(|e| {
        panic!(
            "OIDN_DIR/lib ({}) is not a directory: {e}; run `bash scripts/setup.sh`, which \
             installs Open Image Denoise (pyoidn) into .venv",
            lib.display()
        )
    });
    if !lib.join("libOpenImageDenoise.so").exists()
        && !lib.join("libOpenImageDenoise.so.2").exists()
    {
        println!(
            "cargo:warning={} has no libOpenImageDenoise.so; linking will fail",
            lib.display()
        );
    }
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
}
