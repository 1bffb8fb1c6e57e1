//! Every byte that enters or leaves LightFuse: glTF, USD, EXR, PLY, layouts, datasets and
//! the work folder.

pub mod cameras;
pub mod colmap;
pub mod dataset;
pub mod exr;
pub mod gltf;
pub mod import;
pub mod layout;
pub mod mesh;
pub mod ply;
pub mod usd;
pub mod work;

use crate::error::{Error, Result};
use crate::scene::Scene;
use std::path::{Path, PathBuf};

/// A path's file name without its extension, as a `String` (lossy on non-UTF-8 names); `None`
/// when the path has no file name (`""`, `"/"`, `".."`). The one spelling of this for frames,
/// environments and output files.
pub fn file_stem(path: impl AsRef<Path>) -> Option<String> {
    path.as_ref()
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
}

/// Scene file kinds, chosen by extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneFormat {
    Glb,
    Gltf,
    Usda,
    Ply,
}

impl SceneFormat {
    pub fn from_path(path: &Path) -> Result<SceneFormat> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("glb") => Ok(SceneFormat::Glb),
            Some("gltf") => Ok(SceneFormat::Gltf),
            Some("usda") => Ok(SceneFormat::Usda),
            Some("ply") => Ok(SceneFormat::Ply),
            _ => Err(Error::invalid(
                path,
                "file extension",
                "expected .glb, .gltf, .usda or .ply",
            )),
        }
    }
}

/// Reads a scene (`.glb`, `.gltf`, `.usda`), validated.
pub fn read_scene(path: &Path) -> Result<Scene> {
    let scene =
        match SceneFormat::from_path(path)? {
            SceneFormat::Glb | SceneFormat::Gltf => gltf::read(path)?,
            SceneFormat::Usda => usd::read_usda(path)?,
            SceneFormat::Ply => return Err(Error::invalid(
                path,
                "file extension",
                "PLY is export-only (it has no states or materials); read a .glb, .gltf or .usda",
            )),
        };
    scene.validate(path)?;
    Ok(scene)
}

/// Writes a scene in the format its extension names; nothing is replaced unless the whole file
/// (and its companions) was written.
pub fn write_scene(scene: &Scene, path: &Path) -> Result<()> {
    scene.validate(path)?;
    match SceneFormat::from_path(path)? {
        SceneFormat::Glb => gltf::write_glb(scene, path),
        SceneFormat::Gltf => gltf::write_gltf(scene, path),
        SceneFormat::Usda => usd::write_usda(scene, path),
        SceneFormat::Ply => ply::write(scene, path),
    }
}

/// Files written side by side and made visible together: each is written to a temporary
/// sibling, and only when all are complete are they renamed into place.
#[derive(Default)]
pub struct AtomicFiles {
    pending: Vec<(PathBuf, PathBuf)>,
}

impl AtomicFiles {
    pub fn new() -> Self {
        Self::default()
    }

    /// Writes `bytes` to a temporary sibling of `path`.
    pub fn write(&mut self, path: &Path, bytes: &[u8]) -> Result<()> {
        use std::io::Write;
        self.write_with(path, |w| w.write_all(bytes))
    }

    /// Streams into a temporary sibling of `path` through a buffered writer.
    pub fn write_with(
        &mut self,
        path: &Path,
        f: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> std::io::Result<()>,
    ) -> Result<()> {
        use std::io::Write;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        }
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let tmp = path.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
        let file = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
        let mut w = std::io::BufWriter::with_capacity(1 << 20, file);
        let res = f(&mut w).and_then(|_| w.flush());
        if let Err(e) = res {
            drop(w);
            let _ = std::fs::remove_file(&tmp);
            return Err(Error::io(path, e));
        }
        self.pending.push((tmp, path.to_path_buf()));
        Ok(())
    }

    /// Renames every temporary file into place.
    pub fn commit(mut self) -> Result<()> {
        for (tmp, path) in std::mem::take(&mut self.pending) {
            std::fs::rename(&tmp, &path).map_err(|e| Error::io(&path, e))?;
        }
        Ok(())
    }
}

impl Drop for AtomicFiles {
    fn drop(&mut self) {
        for (tmp, _) in &self.pending {
            let _ = std::fs::remove_file(tmp);
        }
    }
}
