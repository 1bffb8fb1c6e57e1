//! Any bytes given to the glTF reader (GLB by magic, else glTF JSON) give a scene or an error,
//! never a panic, and what it accepts passes validation or fails it cleanly.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("fuzz-input.gltf");
    if let Ok(scene) = lightfuse::io::gltf::read_bytes(path, data) {
        let _ = scene.validate(path);
    }
});
