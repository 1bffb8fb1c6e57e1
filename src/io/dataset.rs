//! `lightfuse-dataset/1` (`dataset.json`, docs/formats.md): states, their ground-truth object poses and
//! environments. Training reads only RGB, depth, normal, masks and cameras; what this module
//! exposes of the ground truth is for evaluation and for oracle scenes that say so.

use crate::error::{Error, Result};
use crate::scene::{Camera, Rigid};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub const DATASET_FORMAT: &str = "lightfuse-dataset/1";

#[derive(Serialize, Deserialize, Debug, Clone)]
pub struct DatasetObject {
    pub id: u32,
    pub name: String,
    /// Ground truth, evaluation only: the object's own frame (origin on its symmetry axes, e.g.
    /// the centre of its base) in the reference state's world.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference_pose: Option<[[f32; 4]; 4]>,
    /// Ground truth, evaluation only: rotations about axes through one point of the object
    /// (its origin unless `offset` says otherwise) that leave its shape and appearance unchanged
    /// (in its frame), so a pose error forgives them ([`crate::eval::pose`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub symmetries: Vec<crate::scene::Symmetry>,
    /// Ground truth, evaluation only: one representative metallic / roughness for the object
    /// ([`ObjectMaterial`]). Absent in datasets written before generate.py recorded it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<ObjectMaterial>,
}

/// Ground truth, evaluation only: an object's Principled BSDF Metallic and Roughness inputs,
/// area-weighted over its faces when its material slots differ (blender/generate.py). Both in
/// [0, 1].
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
pub struct ObjectMaterial {
    pub metallic: f64,
    pub roughness: f64,
}

/// Ground truth provenance of an environment file: the source HDRI, and the rotation about +Y
/// (degrees) and the scale that were *already applied* to the file. Do not apply them again.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq)]
pub struct EnvironmentSource {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotation_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<f64>,
}

#[derive(Serialize, Deserialize, Debug, Clone)]
pub struct Frame {
    /// Linear RGB EXR (channels R, G, B).
    pub file_path: String,
    /// Planar depth EXR (channel Z, metres, 0 = no hit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_file_path: Option<String>,
    /// World-space normal EXR (R, G, B = x, y, z; zero where nothing was hit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normal_file_path: Option<String>,
    /// Sparse planar depth of an imported capture (`lightfuse import colmap`): EXR with `Z`
    /// (metres, 0 = no point at this pixel) and `C` (confidence in (0, 1], from the point's
    /// reprojection error), the SfM points seen in this photo projected into it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sparse_depth_file_path: Option<String>,
    /// 8-bit object-id PNG (0 = background, otherwise a `DatasetObject::id`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mask_path: Option<String>,
    /// Ground truth, evaluation only: base colour EXR (R, G, B = the Principled base colour,
    /// scene-linear; 0 = no hit). Training never reads it ([`Dataset::albedo`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub albedo_file_path: Option<String>,
    #[serde(flatten)]
    pub camera: Camera,
}

impl Frame {
    /// The image file's stem (`test/r_003.exr` → `r_003`), which names everything written per
    /// frame; empty when the path has no file name.
    pub fn stem(&self) -> String {
        super::file_stem(&self.file_path).unwrap_or_default()
    }
}

#[derive(Serialize, Deserialize, Debug, Clone)]
pub struct Relight {
    pub environment: String,
    /// Novel-state synthesis (the paper's Table 2): this run is the test layout under that
    /// training state's own environment; None for an environment no training state saw.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub training_state: Option<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub frames: Vec<Frame>,
}

#[derive(Serialize, Deserialize, Debug, Clone)]
pub struct DatasetState {
    pub name: String,
    pub split: String,
    /// Ground truth: the environment that lit this state, relative to the dataset root
    /// ([`Dataset::environment`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub environment: Option<String>,
    /// Ground truth provenance of `environment` (already applied to the file).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub environment_source: Option<EnvironmentSource>,
    /// Ground truth: each object's rigid transform relative to the reference state (rows).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub object_poses: BTreeMap<String, [[f32; 4]; 4]>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub frames: Vec<Frame>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub relight: Vec<Relight>,
}

#[derive(Serialize, Deserialize, Debug, Clone)]
pub struct Dataset {
    pub format: String,
    /// Must be "+Y".
    pub up: String,
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
        if d.up != "+Y" {
            return Err(Error::invalid(
                &d.file,
                "up",
                format!("expected \"+Y\" (docs/design.md §2), found {:?}", d.up),
            ));
        }
        for (i, o) in d.objects.iter().enumerate() {
            let field = format!("objects[{i}]");
            if !(1..=255).contains(&o.id) {
                return Err(Error::invalid(
                    &d.file,
                    format!("{field}.id"),
                    format!("expected 1..=255 (0 is the background), found {}", o.id),
                ));
            }
            if o.name.is_empty() || o.name == "background" {
                return Err(Error::invalid(
                    &d.file,
                    format!("{field}.name"),
                    "expected a non-empty name other than \"background\"",
                ));
            }
            if let Some(rows) = &o.reference_pose {
                Rigid::from_rows(rows)
                    .map_err(|m| Error::invalid(&d.file, format!("{field}.reference_pose"), m))?;
            }
            for (k, s) in o.symmetries.iter().enumerate() {
                let len = glam::Vec3::from_array(s.axis).length();
                if !(len.is_finite() && len > 0.0) || s.order == 1 {
                    return Err(Error::invalid(
                        &d.file,
                        format!("{field}.symmetries[{k}]"),
                        "expected a non-zero finite axis and order 0 (continuous) or >= 2",
                    ));
                }
                // Pose errors are measured at the point all axes share (eval::pose).
                if s.offset.iter().any(|c| !c.is_finite()) || s.offset != o.symmetries[0].offset {
                    return Err(Error::invalid(
                        &d.file,
                        format!("{field}.symmetries[{k}].offset"),
                        "expected finite coordinates, the same for every symmetry of the object \
                         (its axes meet at one point)",
                    ));
                }
            }
            if let Some(m) = o.material {
                for (name, v) in [("metallic", m.metallic), ("roughness", m.roughness)] {
                    if !(0.0..=1.0).contains(&v) {
                        return Err(Error::invalid(
                            &d.file,
                            format!("{field}.material.{name}"),
                            format!("expected a value in [0, 1], found {v}"),
                        ));
                    }
                }
            }
            if let Some(j) = d.objects[..i]
                .iter()
                .position(|p| p.id == o.id || p.name == o.name)
            {
                return Err(Error::invalid(
                    &d.file,
                    field,
                    format!("expected unique ids and names, but objects[{j}] has the same"),
                ));
            }
        }
        if d.states.is_empty() {
            return Err(Error::invalid(
                &d.file,
                "states",
                "expected at least one state",
            ));
        }
        for (k, st) in d.states.iter().enumerate() {
            if let Some(j) = d.states[..k].iter().position(|p| p.name == st.name) {
                return Err(Error::invalid(
                    &d.file,
                    format!("states[{k}].name"),
                    format!(
                        "expected unique state names, but states[{j}] is also {:?}",
                        st.name
                    ),
                ));
            }
        }
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

    /// Object `o`'s frame in the reference world (ground truth; identity when not recorded).
    pub fn object_frame(&self, o: usize) -> Result<Rigid> {
        match &self.objects[o].reference_pose {
            None => Ok(Rigid::IDENTITY),
            Some(rows) => Rigid::from_rows(rows)
                .map_err(|m| Error::invalid(&self.file, format!("objects[{o}].reference_pose"), m)),
        }
    }

    pub fn path(&self, relative: &str) -> PathBuf {
        self.root.join(relative)
    }

    /// Ground truth, evaluation only: the albedo pass of frame `v` of state `k` (its `frames`,
    /// not its `relight` runs), row-major `w * h` base colours, 0 where nothing was hit; None
    /// when the frame names no albedo file. Errors name the file (missing, not an EXR with R,
    /// G, B, or not its camera's size).
    pub fn albedo(&self, k: usize, v: usize) -> Result<Option<Vec<[f32; 3]>>> {
        let frame = &self.states[k].frames[v];
        let Some(rel) = frame.albedo_file_path.as_deref() else {
            return Ok(None);
        };
        self.frame_rgb(rel, &frame.camera).map(Some)
    }

    /// Ground truth, evaluation only: the `R, G, B` of the image `relative` (a frame's file or
    /// its albedo pass) as row-major pixels, checked to be `camera`'s size (as
    /// [`Dataset::frame_planes`]).
    pub fn frame_rgb(&self, relative: &str, camera: &Camera) -> Result<Vec<[f32; 3]>> {
        let p = self.frame_planes(relative, &["R", "G", "B"], camera)?;
        Ok((0..p[0].len())
            .map(|i| [p[0][i], p[1][i], p[2][i]])
            .collect())
    }

    /// Ground truth, evaluation only: planes `names` of the image `relative` (a frame's file),
    /// checked to be `camera`'s size; errors name the file (missing, a channel absent, or
    /// another size).
    pub fn frame_planes(
        &self,
        relative: &str,
        names: &[&str],
        camera: &Camera,
    ) -> Result<Vec<Vec<f32>>> {
        read_planes(&self.path(relative), names, camera)
    }

    /// The object-id mask of `frame` (0 = background), checked to be its camera's size; None
    /// when the frame names no mask. Errors name the file.
    pub fn frame_mask(&self, frame: &Frame) -> Result<Option<Vec<u8>>> {
        match frame.mask_path.as_deref() {
            Some(rel) => read_mask(&self.path(rel), &frame.camera).map(Some),
            None => Ok(None),
        }
    }

    /// Ground truth, evaluation only: the environment that lit state `k`, read from its
    /// `environment` EXR (named after the state, negative texels set to 0 as for any scene
    /// environment, [`Environment::clamp_negative`]); None when the state records none.
    /// generate.py writes the map already rotated and scaled as Cycles used it (World rotation
    /// 0, strength 1; `environment_source` only records what was applied), so it is in the
    /// frame LightFuse maps environments in and needs no rotation.
    ///
    /// [`Environment::clamp_negative`]: crate::scene::Environment::clamp_negative
    pub fn environment(&self, k: usize) -> Result<Option<crate::scene::Environment>> {
        let Some(rel) = self.states[k].environment.as_deref() else {
            return Ok(None);
        };
        let env = super::exr::read_lighting(&self.path(rel), Some(&self.states[k].name))?;
        Ok(Some(env))
    }

    /// What training needs before any work starts: at least one training state, each with
    /// frames; every frame's RGB, depth, normal and mask present, of its camera's size, masks
    /// naming only known objects; and every object visible in at least one training view.
    /// Returns the observations of the training states, state by state.
    pub fn training_observations(&self) -> Result<Vec<Vec<Observation>>> {
        let train = self.train_states();
        if train.is_empty() {
            return Err(Error::invalid(
                &self.file,
                "states[].split",
                "expected at least one state with split \"train\"",
            ));
        }
        let mut seen = vec![0usize; 256];
        let mut all = Vec::with_capacity(train.len());
        for &k in &train {
            if self.states[k].frames.is_empty() {
                return Err(Error::invalid(
                    &self.file,
                    format!("states[{k}].frames"),
                    format!(
                        "expected at least one frame in training state {:?}",
                        self.states[k].name
                    ),
                ));
            }
            let obs: Vec<Observation> = (0..self.states[k].frames.len())
                .into_par_iter()
                .map(|v| self.observation(k, v))
                .collect::<Result<_>>()?;
            for o in &obs {
                for &m in &o.mask {
                    seen[m as usize] += 1;
                }
            }
            all.push(obs);
        }
        if let Some(o) = self.objects.iter().find(|o| seen[o.id as usize] == 0) {
            return Err(Error::invalid(
                &self.file,
                "objects",
                format!(
                    "object {:?} (id {}) is visible in no training view's mask: nothing to reconstruct it from",
                    o.name, o.id
                ),
            ));
        }
        Ok(all)
    }

    /// Indices of the training states (`split == "train"`), in file order.
    pub fn train_states(&self) -> Vec<usize> {
        (0..self.states.len())
            .filter(|&k| self.states[k].split == "train")
            .collect()
    }

    /// Loads what training may read of frame `v` of state `k`: RGB, depth, normal and object
    /// mask, each checked against the camera's size; the mask's ids against the dataset's
    /// objects. Errors name the image file and what was wrong.
    pub fn observation(&self, k: usize, v: usize) -> Result<Observation> {
        let frame = &self.states[k].frames[v];
        let field = |name: &str| format!("states[{k}].frames[{v}].{name}");
        let camera = frame.camera;
        let n = camera.w as usize * camera.h as usize;
        let need = |p: &Option<String>, name: &str| -> Result<PathBuf> {
            p.as_deref().map(|r| self.path(r)).ok_or_else(|| {
                Error::invalid(
                    &self.file,
                    field(name),
                    "expected a file path (training reads it)",
                )
            })
        };
        let rgb_path = self.path(&frame.file_path);
        let rgb = read_planes(&rgb_path, &["R", "G", "B"], &camera)?;
        let depth_path = need(&frame.depth_file_path, "depth_file_path")?;
        let depth = read_planes(&depth_path, &["Z"], &camera)?;
        let normal_path = need(&frame.normal_file_path, "normal_file_path")?;
        let normal = read_planes(&normal_path, &["R", "G", "B"], &camera)?;
        let mask_path = need(&frame.mask_path, "mask_path")?;
        let mask = read_mask(&mask_path, &camera)?;
        let known: Vec<u32> = self.objects.iter().map(|o| o.id).collect();
        if let Some(bad) = mask
            .iter()
            .find(|&&m| m != 0 && !known.contains(&(m as u32)))
        {
            return Err(Error::invalid(
                &mask_path,
                "pixel values",
                format!(
                    "object id {bad} in the mask, but the dataset's objects have ids {known:?}"
                ),
            ));
        }
        let three = |p: &[Vec<f32>]| -> Vec<[f32; 3]> {
            (0..n).map(|i| [p[0][i], p[1][i], p[2][i]]).collect()
        };
        for (i, z) in depth[0].iter().enumerate() {
            if !(z.is_finite() && *z >= 0.0) {
                return Err(Error::invalid(
                    &depth_path,
                    "Z",
                    format!("expected finite depth >= 0, found {z} at pixel {i}"),
                ));
            }
        }
        Ok(Observation {
            state: k,
            view: v,
            camera,
            rgb: three(&rgb),
            depth: depth.into_iter().next().unwrap_or_default(),
            normal: three(&normal),
            mask,
        })
    }
}

/// One training image with its geometry passes, row-major, `w * h` pixels each.
#[derive(Debug, Clone)]
pub struct Observation {
    pub state: usize,
    pub view: usize,
    pub camera: Camera,
    /// Scene-linear RGB.
    pub rgb: Vec<[f32; 3]>,
    /// Planar depth in metres along the camera's −Z axis; 0 where nothing was hit.
    pub depth: Vec<f32>,
    /// World-space unit normals; zero where nothing was hit.
    pub normal: Vec<[f32; 3]>,
    /// Object id per pixel, 0 = background.
    pub mask: Vec<u8>,
}

fn read_planes(path: &Path, names: &[&str], camera: &Camera) -> Result<Vec<Vec<f32>>> {
    if !path.is_file() {
        return Err(Error::invalid(
            path,
            "file",
            "expected an image here (the dataset names it)",
        ));
    }
    let img = super::exr::read_channels(path)?;
    if (img.width, img.height) != (camera.w as usize, camera.h as usize) {
        return Err(Error::invalid(
            path,
            "size",
            format!(
                "expected {}x{} like its camera, found {}x{}",
                camera.w, camera.h, img.width, img.height
            ),
        ));
    }
    // A one-channel image is accepted whatever its channel is called (the schema allows it).
    if names.len() == 1 && img.channels.len() == 1 {
        return Ok(vec![img.channels[0].1.clone()]);
    }
    names
        .iter()
        .map(|c| {
            img.get(c).map(<[f32]>::to_vec).ok_or_else(|| {
                Error::invalid(
                    path,
                    format!("channel {c}"),
                    "expected this channel in the EXR",
                )
            })
        })
        .collect()
}

fn read_mask(path: &Path, camera: &Camera) -> Result<Vec<u8>> {
    let is_exr = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    if is_exr {
        let plane = read_planes(path, &["Y"], camera)?.remove(0);
        return plane
            .iter()
            .enumerate()
            .map(|(i, &v)| {
                if (0.0..=255.0).contains(&v) && v.fract() == 0.0 {
                    Ok(v as u8)
                } else {
                    Err(Error::invalid(
                        path,
                        "pixel values",
                        format!("expected integer object ids 0..=255, found {v} at pixel {i}"),
                    ))
                }
            })
            .collect();
    }
    if !path.is_file() {
        return Err(Error::invalid(
            path,
            "file",
            "expected an image here (the dataset names it)",
        ));
    }
    let img = image::open(path)
        .map_err(|e| Error::invalid(path, "file", format!("expected an 8-bit PNG mask: {e}")))?;
    if (img.width(), img.height()) != (camera.w, camera.h) {
        return Err(Error::invalid(
            path,
            "size",
            format!(
                "expected {}x{} like its camera, found {}x{}",
                camera.w,
                camera.h,
                img.width(),
                img.height()
            ),
        ));
    }
    Ok(img.into_luma8().into_raw())
}
/// Replaces `scene`'s states by the dataset's, with their ground-truth object poses and
/// environments (resampled to `env_size` if given): the oracle scene of
/// `lightfuse surfelize --dataset`, which checks the renderer against Cycles. A test state's
/// relight runs become a state each (`<state>_<environment stem>`).
pub fn attach_ground_truth(
    scene: &mut crate::scene::Scene,
    dataset: &std::path::Path,
    env_size: Option<(usize, usize)>,
) -> Result<()> {
    use crate::scene::{EnvRef, Rigid, State};
    let d = Dataset::read(dataset)?;
    for c in &scene.components[1..] {
        if !d.objects.iter().any(|o| o.name == c.name) {
            return Err(Error::invalid(
                &d.file,
                "objects",
                format!(
                    "expected an object named {:?} (a component of the mesh scene)",
                    c.name
                ),
            ));
        }
    }
    let mut env_index = std::collections::HashMap::new();
    let mut environments = Vec::new();
    let mut load_env = |rel: &str| -> Result<EnvRef> {
        if let Some(&index) = env_index.get(rel) {
            return Ok(EnvRef {
                index,
                rotation_deg: 0.0,
            });
        }
        let path = d.path(rel);
        let mut env = super::exr::read_lighting(&path, None)?;
        if let Some((w, h)) = env_size {
            env = env.resample(w, h);
        }
        environments.push(env);
        env_index.insert(rel.to_string(), environments.len() - 1);
        // The generator writes environments already rotated (dataset.json environment_source).
        Ok(EnvRef {
            index: environments.len() - 1,
            rotation_deg: 0.0,
        })
    };
    let mut states = Vec::new();
    for (k, s) in d.states.iter().enumerate() {
        let transforms = scene
            .components
            .iter()
            .enumerate()
            .map(|(i, c)| {
                if i == 0 {
                    Ok(Rigid::IDENTITY)
                } else {
                    d.object_pose(k, &c.name)
                }
            })
            .collect::<Result<Vec<_>>>()?;
        if let Some(env) = &s.environment {
            states.push(State {
                name: s.name.clone(),
                transforms: transforms.clone(),
                environment: Some(load_env(env)?),
            });
        } else if s.relight.is_empty() {
            states.push(State {
                name: s.name.clone(),
                transforms: transforms.clone(),
                environment: None,
            });
        }
        for r in &s.relight {
            let e = load_env(&r.environment)?;
            let stem = super::file_stem(&r.environment).unwrap_or_default();
            states.push(State {
                name: format!("{}_{stem}", s.name),
                transforms: transforms.clone(),
                environment: Some(e),
            });
        }
    }
    let reference = states
        .iter()
        .position(|s| s.transforms.iter().all(Rigid::is_identity))
        .unwrap_or(0);
    scene.states = states;
    scene.environments = environments;
    scene.reference_state = reference;
    Ok(())
}

/// Views with index ≡ 0 (mod HOLDOUT) are withheld from training (every stage holds out the
/// same views, so their held-out figures are comparable).
pub const HOLDOUT: usize = 8;

/// Splits the observations of each training state into (training, held-out): views with index
/// ≡ 0 (mod [`HOLDOUT`]) are held out.
pub fn split(obs: Vec<Vec<Observation>>) -> (Vec<Vec<Observation>>, Vec<Vec<Observation>>) {
    let mut train = Vec::new();
    let mut held = Vec::new();
    for state in obs {
        let (h, t): (Vec<_>, Vec<_>) = state.into_iter().partition(|o| o.view % HOLDOUT == 0);
        train.push(t);
        held.push(h);
    }
    (train, held)
}
