//! PLY export.
use crate::error::{Error, Result};
use crate::scene::Scene;
use std::path::Path;
pub fn write(_scene: &Scene, path: &Path) -> Result<()> {
    Err(Error::invalid(path, "format", "todo"))
}
