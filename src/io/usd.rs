//! OpenUSD `.usda` (helper in progress).
use crate::error::{Error, Result};
use crate::scene::Scene;
use std::path::Path;

pub fn write_usda(_scene: &Scene, path: &Path) -> Result<()> {
    Err(Error::invalid(
        path,
        "format",
        "USD writing is not built yet",
    ))
}

pub fn read_usda(path: &Path) -> Result<Scene> {
    Err(Error::invalid(
        path,
        "format",
        "USD reading is not built yet",
    ))
}
