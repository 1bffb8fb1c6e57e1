//! Cameras to render: a dataset's frames (one state's, or all) or a cameras.json, each with the
//! name its output files take.

use crate::error::{Error, Result};
use crate::io::dataset::{Dataset, Frame, DATASET_FORMAT};
use crate::scene::Camera;
use std::path::{Path, PathBuf};

/// A camera and the name its files take.
#[derive(Clone, Debug)]
pub struct View {
    pub name: String,
    pub camera: Camera,
}

/// `{"frames": [...]}` of a cameras file.
#[derive(serde::Deserialize)]
struct CameraFile {
    frames: Vec<Frame>,
}

/// The cameras at `path`: a dataset's frames (`frames` names a state or is `all`; by default the
/// state named `state_name` if the dataset has it, else its first state), or every frame of a
/// cameras.json (`{"frames": [...]}` with dataset frame fields). Each is named after its file
/// stem, or after its path with `/` → `_` when two stems clash. Errors name `--frames` as the
/// option that selects.
pub fn read_views(path: &Path, frames_arg: Option<&str>, state_name: &str) -> Result<Vec<View>> {
    let is_dataset = path.is_dir() || {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let v: serde_json::Value = serde_json::from_slice(&bytes)
            .map_err(|e| Error::invalid(path, "JSON", format!("expected valid JSON: {e}")))?;
        v.get("format").and_then(|f| f.as_str()) == Some(DATASET_FORMAT)
    };
    // (frame, state name or "", index) of each selected frame.
    let mut frames: Vec<(Frame, String, PathBuf)> = Vec::new();
    if is_dataset {
        let d = Dataset::read(path)?;
        let state_frames = |k: usize| -> Vec<Frame> {
            let s = &d.states[k];
            if s.frames.is_empty() {
                s.relight.iter().flat_map(|r| r.frames.clone()).collect()
            } else {
                s.frames.clone()
            }
        };
        let chosen: Vec<usize> = match frames_arg {
            Some("all") => (0..d.states.len()).collect(),
            Some(name) => vec![d
                .states
                .iter()
                .position(|s| s.name == name)
                .ok_or_else(|| {
                    let names: Vec<_> = d.states.iter().map(|s| s.name.as_str()).collect();
                    Error::invalid(
                        &d.file,
                        "states",
                        format!("--frames {name:?}: expected \"all\" or one of {names:?}"),
                    )
                })?],
            None => vec![d
                .states
                .iter()
                .position(|s| s.name == state_name)
                .unwrap_or(0)],
        };
        for k in chosen {
            for f in state_frames(k) {
                frames.push((f, d.states[k].name.clone(), d.file.clone()));
            }
        }
        // Relight frames are not validated by Dataset::read.
        for (i, (f, s, file)) in frames.iter().enumerate() {
            f.camera
                .validate(file, &format!("states.{s}.frames[{i}]"))?;
        }
    } else {
        if frames_arg.is_some() {
            return Err(Error::Usage(
                "--frames selects a dataset state's frames; --cameras is not a dataset".into(),
            ));
        }
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let c: CameraFile = serde_json::from_slice(&bytes).map_err(|e| {
            Error::invalid(
                path,
                "frames",
                format!("expected {{\"frames\": [...]}} with dataset frame fields: {e}"),
            )
        })?;
        for (i, f) in c.frames.iter().enumerate() {
            f.camera.validate(path, &format!("frames[{i}]"))?;
        }
        frames = c
            .frames
            .into_iter()
            .map(|f| (f, String::new(), path.to_path_buf()))
            .collect();
    }
    if frames.is_empty() {
        return Err(Error::invalid(
            path,
            "frames",
            "expected at least one camera frame",
        ));
    }
    let stems: Vec<String> = frames.iter().map(|(f, _, _)| f.stem()).collect();
    let unique = {
        let mut s = stems.clone();
        s.sort();
        s.dedup();
        s.len() == stems.len() && stems.iter().all(|s| !s.is_empty())
    };
    Ok(frames
        .into_iter()
        .zip(stems)
        .enumerate()
        .map(|(i, ((f, _, _), stem))| {
            let name = if unique {
                stem
            } else {
                let p = Path::new(&f.file_path).with_extension("");
                let flat = p.to_string_lossy().replace(['/', '\\'], "_");
                if flat.is_empty() {
                    format!("{i:03}")
                } else {
                    flat
                }
            };
            View {
                name,
                camera: f.camera,
            }
        })
        .collect())
}
