//! `lightfuse-dataset/1` (`dataset.json`, DESIGN §3): states, their ground-truth object poses and
//! environments. Training reads only RGB, depth, normal, masks and cameras; what this module
//! exposes of the ground truth is for evaluation and for oracle scenes that say so.

use crate::error::{Error, Result};
use crate::scene::{Camera, Rigid};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub const DATASET_FORMAT: &str = "lightfuse-dataset/1";

#[derive(Deserialize, Debug, Clone)]
pub struct DatasetObject {
    pub id: u32,
    pub name: String,
}

#[derive(Deserialize, Debug, Clone)]
pub struct Frame {
    pub file_path: String,
    #[serde(flatten)]
    pub camera: Camera,
}

#[derive(Deserialize, Debug, Clone)]
pub struct Relight {
    pub environment: String,
    #[serde(default)]
    pub frames: Vec<Frame>,
}

#[derive(Deserialize, Debug, Clone)]
pub struct DatasetState {
    pub name: String,
    pub split: String,
    /// Ground truth: the environment that lit this state.
    pub environment: Option<String>,
    /// Ground truth: each object's rigid transform relative to the reference state (rows).
    #[serde(default)]
    pub object_poses: BTreeMap<String, [[f32; 4]; 4]>,
    #[serde(default)]
    pub frames: Vec<Frame>,
    #[serde(default)]
    pub relight: Vec<Relight>,
}

#[derive(Deserialize, Debug, Clone)]
pub struct Dataset {
    pub format: String,
    pub objects: Vec<DatasetObject>,
    pub states: Vec<DatasetState>,
    /// The folder holding `dataset.json`; every path in the file is relative to it.
    #[serde(skip)]
    pub root: PathBuf,
    #[serde(skip)]
    pub file: PathBuf,
}

impl Dataset {
    /// Reads `dataset.json`, or the `dataset.json` inside a folder.
    pub fn read(path: &Path) -> Result<Dataset> {
        let file = if path.is_dir() {
            path.join("dataset.json")
        } else {
            path.to_path_buf()
        };
        let bytes = std::fs::read(&file).map_err(|e| Error::io(&file, e))?;
        let mut d: Dataset = serde_json::from_slice(&bytes).map_err(|e| {
            Error::invalid(
                &file,
                "dataset.json",
                format!("expected a {DATASET_FORMAT} dataset: {e}"),
            )
        })?;
        if d.format != DATASET_FORMAT {
            return Err(Error::invalid(
                &file,
                "format",
                format!("expected {DATASET_FORMAT:?}, found {:?}", d.format),
            ));
        }
        d.root = file.parent().unwrap_or(Path::new("")).to_path_buf();
        d.file = file;
        for (k, s) in d.states.iter().enumerate() {
            for name in s.object_poses.keys() {
                if !d.objects.iter().any(|o| &o.name == name) {
                    return Err(Error::invalid(
                        &d.file,
                        format!("states[{k}].object_poses.{name}"),
                        "expected one of the dataset's objects",
                    ));
                }
            }
            for (i, f) in s.frames.iter().enumerate() {
                f.camera
                    .validate(&d.file, &format!("states[{k}].frames[{i}]"))?;
            }
        }
        Ok(d)
    }

    /// Ground-truth pose of `object` in state `k` (identity when not recorded).
    pub fn object_pose(&self, k: usize, object: &str) -> Result<Rigid> {
        match self.states[k].object_poses.get(object) {
            None => Ok(Rigid::IDENTITY),
            Some(rows) => Rigid::from_rows(rows).map_err(|m| {
                Error::invalid(&self.file, format!("states[{k}].object_poses.{object}"), m)
            }),
        }
    }

    pub fn path(&self, relative: &str) -> PathBuf {
        self.root.join(relative)
    }
}
