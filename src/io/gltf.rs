//! glTF.
use crate::error::{Error, Result};
use crate::scene::Scene;
use std::path::Path;
pub fn read(path: &Path) -> Result<Scene> {
    Err(Error::invalid(path, "format", "todo"))
}
pub fn write_glb(_scene: &Scene, path: &Path) -> Result<()> {
    Err(Error::invalid(path, "format", "todo"))
}
pub fn write_gltf(_scene: &Scene, path: &Path) -> Result<()> {
    Err(Error::invalid(path, "format", "todo"))
}
