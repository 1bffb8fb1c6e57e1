//! `lightfuse import colmap | nerfstudio`: a capture made elsewhere in, an ordinary LightFuse
//! dataset (docs/formats.md) out, so every later command reads it unchanged. Each source is
//! turned into a list of [`Shot`]s (a photo, its lens, its pose, its state); what follows is
//! shared (docs/real-captures.md):
//!
//! - **States** from the folder holding each photo (`state1/IMG_0001.jpg` belongs to
//!   `state1`), or from a mapping file; `--test-states` names the held-out ones.
//! - **One world.** With COLMAP, every state must share triangulated points with the others:
//!   states registered by separate SfM runs have unrelated frames, and are refused.
//! - **Axes.** Poses become camera-to-world with OpenGL axes (−Z forward, +Y up); the world is
//!   turned so gravity is −Y (from `--up`, or the dominant supporting plane, [`estimate_up`]),
//!   scaled to metres by `--scale` (or `--scale-points`: two points a known distance apart),
//!   and moved so that plane is y = 0 under the points' middle.
//!   The similarity is kept in `import.json`.
//! - **Lenses.** A distorted camera's photo is resampled into a pinhole image of the same size
//!   ([`Lens::pinhole`]); spherical cameras are refused.
//! - **Pixels.** 8- and 16-bit sRGB JPEG / PNG are linearised (the sRGB curve: a photo's own
//!   tone curve is not known) and written as float EXR; masks (8-bit PNG of object ids) and
//!   depth are resampled by nearest neighbour (a blend of two objects' ids or depths is
//!   neither).
//!
//! Not yet: normals, and depth for COLMAP captures. Training needs both, so it refuses such a
//! dataset, naming the field, until sparse depth from the SfM points and the 2DGS
//! depth–normal self-consistency replace them.

use super::colmap::lens::{Lens, LensModel, Pinhole};
use super::colmap::read_model;
use super::dataset::{DatasetObject, DatasetState, Frame, DATASET_FORMAT};
use crate::error::{Error, Result};
use crate::scene::Camera;
use glam::{DMat3, DVec3};
use rayon::prelude::*;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// What every import is asked, whatever the source.
#[derive(Clone, Debug, Default)]
pub struct ImportOptions {
    /// A JSON object mapping photo names (as the source names them) to state names, instead
    /// of the photos' folders.
    pub states: Option<PathBuf>,
    /// States held out for evaluation (`split: "test"`).
    pub test_states: Vec<String>,
    /// The world's up direction in the source's frame; estimated when None.
    pub up: Option<[f64; 3]>,
    /// Metres per source unit.
    pub scale: Option<f64>,
    /// Two points a known distance apart, instead of `scale`.
    pub scale_points: Option<ScalePoints>,
    /// The dataset folder to write (new, empty, or left by an interrupted import).
    pub out: PathBuf,
    pub quiet: bool,
}

/// Two points of the capture a known distance apart (a tape measure's two ends, a marker's
/// corners): the scale is `metres` over their distance in source units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScalePoints {
    pub a: MarkedPoint,
    pub b: MarkedPoint,
    pub metres: f64,
}

impl ScalePoints {
    /// `--scale-points A B METRES`' three values.
    pub fn parse(values: &[String]) -> Result<ScalePoints> {
        let [a, b, m] = values else {
            return Err(Error::Usage(format!(
                "--scale-points: expected A B METRES, found {} values",
                values.len()
            )));
        };
        let point = |s: &str| {
            s.parse::<MarkedPoint>()
                .map_err(|e| Error::Usage(format!("--scale-points: {e}")))
        };
        let metres = m.trim().parse::<f64>().map_err(|_| {
            Error::Usage(format!(
                "--scale-points: expected the points' distance in metres, found {m:?}"
            ))
        })?;
        Ok(ScalePoints {
            a: point(a)?,
            b: point(b)?,
            metres,
        })
    }
}

/// A point of the capture, as a user can read it off their tools.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MarkedPoint {
    /// Coordinates in the source's world (a point-cloud viewer's pick).
    Source([f64; 3]),
    /// A COLMAP 3D point by its id (`points3D`'s `POINT3D_ID`, as COLMAP's GUI shows on a
    /// click).
    Point(u64),
}

impl std::str::FromStr for MarkedPoint {
    type Err = String;
    /// `X,Y,Z` or `point:ID`.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let expected = || format!("expected X,Y,Z or point:ID (a COLMAP 3D point), found {s:?}");
        if let Some(id) = s.strip_prefix("point:") {
            return id
                .trim()
                .parse()
                .map(MarkedPoint::Point)
                .map_err(|_| expected());
        }
        let v: Vec<f64> = s
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .map_err(|_| expected())?;
        match v.as_slice() {
            [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok(MarkedPoint::Source([*x, *y, *z])),
            _ => Err(expected()),
        }
    }
}

/// `lightfuse import colmap`.
#[derive(Clone, Debug, Default)]
pub struct ColmapImport {
    /// A sparse model folder (`sparse/0`).
    pub model: PathBuf,
    /// The folder COLMAP's image names are relative to.
    pub images: PathBuf,
    /// A folder of id masks, `<image name>.png` each.
    pub masks: Option<PathBuf>,
    pub options: ImportOptions,
}

/// `lightfuse import nerfstudio`.
#[derive(Clone, Debug, Default)]
pub struct NerfstudioImport {
    /// The `transforms.json`.
    pub transforms: PathBuf,
    /// Metres per stored depth unit (nerfstudio's `depth_unit_scale_factor`, 1e-3 for its
    /// millimetre PNGs).
    pub depth_unit_scale: f64,
    pub options: ImportOptions,
}

/// One photo to import, from any source.
#[derive(Clone, Debug)]
pub struct Shot {
    /// The photo's name as the source gives it (COLMAP's image name, nerfstudio's
    /// `file_path`): the key of `--states` files and of the output's order.
    pub name: String,
    /// The source file and field that named the photo, for errors about it.
    pub named_in: (PathBuf, String),
    /// The source file and field that define the photo's camera, for errors about it.
    pub lens_in: (PathBuf, String),
    pub photo: PathBuf,
    pub mask: Option<PathBuf>,
    /// Planar depth in stored units (× `depth_unit_scale` = source units).
    pub depth: Option<PathBuf>,
    pub lens: Lens,
    /// Camera-to-world rotation with OpenGL axes (+Y up, −Z forward), in the source's world.
    pub rotation: DMat3,
    pub centre: DVec3,
}

/// The shots of a source, the 3D points it has (for the up estimate), and what
/// `import.json` should say of it.
struct Capture {
    source: &'static str,
    shots: Vec<Shot>,
    points: Vec<DVec3>,
    /// Per point, the source's id for it (COLMAP's `POINT3D_ID`; empty when the source has
    /// none), for `--scale-points`.
    point_ids: Vec<u64>,
    /// Per point, the shots (indices) that see it, when the source keeps tracks (COLMAP), with
    /// the file they came from: the one-world check and each photo's sparse depth.
    tracks: Option<(PathBuf, Vec<Vec<usize>>)>,
    /// Per point, its mean reprojection error in pixels (COLMAP's `ERROR`), beside `tracks`.
    point_errors: Vec<f64>,
    depth_unit_scale: f64,
    provenance: serde_json::Value,
}

/// The similarity from the source's world to the dataset's: `x' = scale · R (x − origin)`.
#[derive(Clone, Copy, Debug)]
pub struct WorldFrame {
    pub rotation: DMat3,
    pub origin: DVec3,
    pub scale: f64,
    /// How the up direction was found.
    pub up_source: &'static str,
}

impl WorldFrame {
    pub fn point(&self, x: DVec3) -> DVec3 {
        self.scale * (self.rotation * (x - self.origin))
    }
}

/// What the import wrote, for the CLI to print.
#[derive(Clone, Debug)]
pub struct ImportSummary {
    pub dataset: PathBuf,
    pub states: Vec<(String, String, usize)>,
    pub objects: Vec<u8>,
    pub undistorted: usize,
    pub frame: WorldFrame,
}

/// COLMAP's world-to-camera (+Y down, +Z forward) as camera-to-world with OpenGL axes:
/// the rotation Rᵀ with the camera's y and z axes negated, and the centre −Rᵀt.
fn colmap_pose(im: &super::colmap::ColmapImage) -> (DMat3, DVec3) {
    let m = im.cam_from_world();
    let r = DMat3::from_cols(
        DVec3::new(m[0][0], m[1][0], m[2][0]),
        DVec3::new(m[0][1], m[1][1], m[2][1]),
        DVec3::new(m[0][2], m[1][2], m[2][2]),
    );
    let rt = r.transpose();
    (
        DMat3::from_cols(rt.x_axis, -rt.y_axis, -rt.z_axis),
        DVec3::from(im.centre()),
    )
}

/// The shots of a COLMAP model. Checks what only COLMAP can tell: that the states share
/// triangulated points (one world).
fn colmap_capture(a: &ColmapImport) -> Result<Capture> {
    let model = read_model(&a.model)?;
    if model.images.is_empty() {
        return Err(Error::invalid(
            model.file("images"),
            "images",
            "expected at least one registered image",
        ));
    }
    let index: BTreeMap<u32, usize> = model
        .images
        .keys()
        .enumerate()
        .map(|(k, id)| (*id, k))
        .collect();
    let tracks = model
        .points
        .iter()
        .map(|p| p.track.iter().map(|(im, _)| index[im]).collect())
        .collect();
    let shots = model
        .images
        .values()
        .map(|im| {
            let (rotation, centre) = colmap_pose(im);
            Shot {
                name: im.name.clone(),
                named_in: (model.file("images"), format!("image {}", im.id)),
                lens_in: (model.file("cameras"), format!("camera {}", im.camera_id)),
                photo: a.images.join(&im.name),
                mask: a.masks.as_ref().map(|d| d.join(format!("{}.png", im.name))),
                depth: None,
                lens: model.cameras[&im.camera_id].clone(),
                rotation,
                centre,
            }
        })
        .collect();
    Ok(Capture {
        source: "colmap",
        shots,
        points: model.points.iter().map(|p| DVec3::from(p.xyz)).collect(),
        point_ids: model.points.iter().map(|p| p.id).collect(),
        tracks: Some((model.file("points3D"), tracks)),
        point_errors: model.points.iter().map(|p| p.error).collect(),
        depth_unit_scale: 1.0,
        provenance: serde_json::json!({"model": a.model, "images": a.images, "masks": a.masks,
            "points": model.points.len()}),
    })
}

/// One world: every state shares a point with another state (a point whose track has shots of
/// two states). Without any, the states were registered apart and their frames are unrelated.
fn check_one_world(file: &Path, tracks: &[Vec<usize>], states: &[String]) -> Result<()> {
    let names: BTreeSet<&String> = states.iter().collect();
    if names.len() < 2 {
        return Ok(());
    }
    let mut shared: BTreeMap<&String, usize> = names.iter().map(|n| (*n, 0)).collect();
    for track in tracks {
        let seen: BTreeSet<&String> = track.iter().map(|&k| &states[k]).collect();
        if seen.len() >= 2 {
            for s in seen {
                *shared.get_mut(s).unwrap() += 1;
            }
        }
    }
    if let Some((s, _)) = shared.iter().find(|(_, &n)| n == 0) {
        return Err(Error::invalid(
            file,
            "tracks",
            format!(
                "state {s:?} shares no triangulated point with the other states: the states were \
                 registered separately and their worlds are unrelated. Run one SfM over every \
                 capture (mask the moved objects out of feature matching)"
            ),
        ));
    }
    Ok(())
}

/// nerfstudio's `camera_model` and distortion keys as a COLMAP lens. nerfstudio's OPENCV is
/// OpenCV's radial k1..k3 with tangential p1, p2 (FULL_OPENCV with k4..k6 = 0); its
/// FISHEYE624 is Project Aria's model (RAD_TAN_THIN_PRISM_FISHEYE).
fn nerfstudio_lens(
    file: &Path,
    field: &str,
    v: &dyn Fn(&str) -> Option<f64>,
    w: u32,
    h: u32,
    model: &str,
) -> Result<Lens> {
    let need = |k: &str| {
        v(k).ok_or_else(|| {
            Error::invalid(
                file,
                format!("{field}.{k}"),
                "expected a number (nerfstudio's intrinsics)",
            )
        })
    };
    let d = |k: &str| v(k).unwrap_or(0.0);
    let (fx, fy, cx, cy) = (need("fl_x")?, need("fl_y")?, need("cx")?, need("cy")?);
    let (lens_model, params) = match model {
        "PINHOLE" | "SIMPLE_PINHOLE" => (LensModel::Pinhole, vec![fx, fy, cx, cy]),
        "OPENCV" | "PERSPECTIVE" => {
            let k = [d("k1"), d("k2"), d("p1"), d("p2"), d("k3")];
            if k.iter().all(|x| *x == 0.0) {
                (LensModel::Pinhole, vec![fx, fy, cx, cy])
            } else {
                (
                    LensModel::FullOpenCv,
                    vec![fx, fy, cx, cy, k[0], k[1], k[2], k[3], k[4], 0.0, 0.0, 0.0],
                )
            }
        }
        "OPENCV_FISHEYE" | "FISHEYE" => (
            LensModel::OpenCvFisheye,
            vec![fx, fy, cx, cy, d("k1"), d("k2"), d("k3"), d("k4")],
        ),
        "FISHEYE624" => (
            LensModel::RadTanThinPrismFisheye,
            vec![
                fx,
                fy,
                cx,
                cy,
                d("k1"),
                d("k2"),
                d("k3"),
                d("k4"),
                d("k5"),
                d("k6"),
                d("p1"),
                d("p2"),
                d("s1"),
                d("s2"),
                d("s3"),
                d("s4"),
            ],
        ),
        "EQUIRECTANGULAR"
        | "OMNIDIRECTIONALSTEREO_L"
        | "OMNIDIRECTIONALSTEREO_R"
        | "VR180_L"
        | "VR180_R" => {
            return Err(Error::invalid(file, format!("{field}.camera_model"), format!("{model} cameras are refused: LightFuse's cameras are pinholes; cut the panoramas into perspective views")));
        }
        other => {
            return Err(Error::invalid(
                file,
                format!("{field}.camera_model"),
                format!("expected PINHOLE, OPENCV, OPENCV_FISHEYE or FISHEYE624, found {other:?}"),
            ));
        }
    };
    if let Some(bad) = params.iter().find(|p| !p.is_finite()) {
        return Err(Error::invalid(
            file,
            field,
            format!("expected finite intrinsics, found {bad}"),
        ));
    }
    Ok(Lens {
        model: lens_model,
        width: w,
        height: h,
        params,
    })
}

/// The shots of a nerfstudio `transforms.json`: shared intrinsics at the top, any of them
/// overridden per frame; `transform_matrix` camera-to-world with OpenGL axes (nerfstudio's
/// convention, ours too); `mask_path` and `depth_file_path` relative to the file's folder.
fn nerfstudio_capture(a: &NerfstudioImport) -> Result<Capture> {
    let file = &a.transforms;
    let bytes = std::fs::read(file).map_err(|e| Error::io(file, e))?;
    let root: serde_json::Value =
        serde_json::from_slice(&bytes).map_err(|e| Error::invalid(file, "json", e.to_string()))?;
    let dir = file.parent().unwrap_or(Path::new("."));
    let frames = root["frames"]
        .as_array()
        .filter(|f| !f.is_empty())
        .ok_or_else(|| Error::invalid(file, "frames", "expected a non-empty list of frames"))?;
    let mut shots = Vec::with_capacity(frames.len());
    for (i, f) in frames.iter().enumerate() {
        let field = format!("frames[{i}]");
        let v = |k: &str| f[k].as_f64().or(root[k].as_f64());
        let size = |k: &str| -> Result<u32> {
            v(k).filter(|x| *x >= 1.0 && x.fract() == 0.0 && *x < 1e6)
                .map(|x| x as u32)
                .ok_or_else(|| {
                    Error::invalid(
                        file,
                        format!("{field}.{k}"),
                        "expected the image size in pixels (per frame or shared)",
                    )
                })
        };
        let (w, h) = (size("w")?, size("h")?);
        let model = f["camera_model"]
            .as_str()
            .or(root["camera_model"].as_str())
            .unwrap_or("OPENCV");
        let lens = nerfstudio_lens(file, &field, &v, w, h, model)?;
        let path = |k: &str| -> Result<Option<PathBuf>> {
            match &f[k] {
                serde_json::Value::Null => Ok(None),
                serde_json::Value::String(s) => Ok(Some(dir.join(s))),
                _ => Err(Error::invalid(
                    file,
                    format!("{field}.{k}"),
                    "expected a path",
                )),
            }
        };
        let name = f["file_path"].as_str().ok_or_else(|| {
            Error::invalid(
                file,
                format!("{field}.file_path"),
                "expected the photo's path",
            )
        })?;
        let m: Option<[[f64; 4]; 4]> = serde_json::from_value(f["transform_matrix"].clone()).ok();
        let Some(m) = m else {
            return Err(Error::invalid(
                file,
                format!("{field}.transform_matrix"),
                "expected a 4x4 camera-to-world matrix (rows)",
            ));
        };
        let rotation = DMat3::from_cols(
            DVec3::new(m[0][0], m[1][0], m[2][0]),
            DVec3::new(m[0][1], m[1][1], m[2][1]),
            DVec3::new(m[0][2], m[1][2], m[2][2]),
        );
        // Scale in the rotation (nerfstudio's scene normalisation keeps it rigid; anything
        // else is not a camera) is refused.
        let ortho = (rotation.transpose() * rotation - DMat3::IDENTITY)
            .to_cols_array()
            .iter()
            .map(|x| x.abs())
            .fold(0.0, f64::max);
        if !(ortho < 1e-4 && rotation.determinant() > 0.0) {
            return Err(Error::invalid(
                file,
                format!("{field}.transform_matrix"),
                "expected a rigid camera-to-world (a rotation and a translation)",
            ));
        }
        shots.push(Shot {
            name: name.to_string(),
            named_in: (file.clone(), format!("{field}.file_path")),
            lens_in: (file.clone(), field.clone()),
            photo: dir.join(name),
            mask: path("mask_path")?,
            depth: path("depth_file_path")?,
            lens,
            rotation,
            centre: DVec3::new(m[0][3], m[1][3], m[2][3]),
        });
    }
    // `ply_file_path` (the SfM points some exports carry) is not read yet: the up estimate
    // uses the cameras alone, so give --up when the photos were not taken upright.
    Ok(Capture {
        source: "nerfstudio",
        shots,
        points: Vec::new(),
        point_ids: Vec::new(),
        tracks: None,
        point_errors: Vec::new(),
        depth_unit_scale: a.depth_unit_scale,
        provenance: serde_json::json!({"transforms": file, "depth_unit_scale": a.depth_unit_scale}),
    })
}

/// The state of a shot: its `--states` entry, or the name of the folder holding the photo.
fn state_of(map: Option<&(PathBuf, BTreeMap<String, String>)>, shot: &Shot) -> Result<String> {
    if let Some((file, map)) = map {
        let state = map.get(&shot.name).ok_or_else(|| {
            Error::invalid(
                file,
                &shot.name,
                "expected this photo's state (the source names the photo)",
            )
        })?;
        // A state is a folder of the output: one plain name, never a path out of it.
        let plain = !state.is_empty()
            && state != "."
            && state != ".."
            && !state.contains(['/', '\\'])
            && !state.contains('\0');
        if !plain {
            return Err(Error::invalid(
                file,
                &shot.name,
                format!("expected a state name (no '/' or '\\', not '.' or '..'), found {state:?}"),
            ));
        }
        return Ok(state.clone());
    }
    let folder = Path::new(&shot.name)
        .parent()
        .and_then(|p| p.file_name())
        .map(|s| s.to_string_lossy().into_owned());
    folder
        .filter(|s| !s.is_empty() && s != "." && s != "..")
        .ok_or_else(|| {
            Error::invalid(
                &shot.named_in.0,
                format!("{}.name", shot.named_in.1),
                format!(
                "{:?} is in no state folder: keep each capture's photos in a folder named after \
                 its state (state0/IMG.jpg), or give --states FILE",
                shot.name
            ),
            )
        })
}
/// A small deterministic generator for RANSAC (splitmix64): the same import every run.
struct SplitMix(u64);
impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

/// The world's up direction, in the source's frame, a point on the supporting plane when one
/// was found, and where the direction came from.
///
/// First guess: the mean of the cameras' up axes (photos are mostly taken upright). Then the
/// dominant supporting plane: by RANSAC over the 3D points, the plane with the most points
/// within 1 % of the points' spread whose normal is within 30° of the guess (walls are further
/// off), refined by least squares over its points and turned to the cameras' side. The scenes
/// LightFuse is for stand on a floor or a table, so that plane is gravity's; with fewer than
/// 50 points the guess is kept.
pub fn estimate_up(shots: &[Shot], pts: &[DVec3]) -> (DVec3, Option<DVec3>, &'static str) {
    let guess = shots
        .iter()
        .map(|s| s.rotation.y_axis)
        .sum::<DVec3>()
        .normalize_or(DVec3::Y);
    if pts.len() < 50 {
        return (
            guess,
            None,
            "the cameras' mean up axis (too few points for a plane)",
        );
    }
    let mid = pts.iter().copied().sum::<DVec3>() / pts.len() as f64;
    let mut d: Vec<f64> = pts.iter().map(|p| (*p - mid).length()).collect();
    let spread = crate::stats::median(&mut d).unwrap_or(1.0);
    let tol = 0.01 * spread;
    let mut rng = SplitMix(0x1f_2e3d);
    let mut best: Option<(usize, DVec3, DVec3)> = None;
    for _ in 0..2000 {
        let (a, b, c) = (
            pts[rng.below(pts.len())],
            pts[rng.below(pts.len())],
            pts[rng.below(pts.len())],
        );
        let n = (b - a).cross(c - a);
        if n.length() < 1e-12 * spread * spread {
            continue;
        }
        let n = n.normalize();
        let n = if n.dot(guess) < 0.0 { -n } else { n };
        if n.dot(guess) < 30f64.to_radians().cos() {
            continue;
        }
        let count = pts.iter().filter(|p| (**p - a).dot(n).abs() < tol).count();
        if best.is_none_or(|(k, _, _)| count > k) {
            best = Some((count, n, a));
        }
    }
    let Some((_, n0, a0)) = best else {
        return (guess, None, "the cameras' mean up axis (no plane near it)");
    };
    let inl: Vec<DVec3> = pts
        .iter()
        .copied()
        .filter(|p| (*p - a0).dot(n0).abs() < tol)
        .collect();
    let c = inl.iter().copied().sum::<DVec3>() / inl.len() as f64;
    let mut cov = DMat3::ZERO;
    for p in &inl {
        let q = *p - c;
        cov += DMat3::from_cols(q * q.x, q * q.y, q * q.z);
    }
    let n = smallest_eigenvector(cov);
    let n = if n.dot(guess) < 0.0 { -n } else { n };
    (
        n,
        Some(c),
        "the dominant supporting plane (RANSAC over the SfM points)",
    )
}

/// The eigenvector of a symmetric 3x3 with the smallest eigenvalue, by inverse iteration on
/// the matrix shifted by its trace (so the smallest becomes the largest in magnitude).
fn smallest_eigenvector(m: DMat3) -> DVec3 {
    let t = m.x_axis.x + m.y_axis.y + m.z_axis.z;
    let shifted = DMat3::from_diagonal(DVec3::splat(t)) - m;
    let mut v = DVec3::new(0.3, 0.9, 0.2).normalize();
    for _ in 0..200 {
        v = (shifted * v).normalize_or(DVec3::Y);
    }
    v
}

/// The rotation taking `up` to +Y by the shortest arc.
fn rotation_to_y(up: DVec3) -> DMat3 {
    let q = glam::DQuat::from_rotation_arc(up.normalize(), DVec3::Y);
    DMat3::from_quat(q)
}

/// The similarity into the dataset's world: gravity −Y, metres, origin on the supporting plane
/// under the points' median (or under the cameras' median when there are no points).
pub fn world_frame(
    shots: &[Shot],
    points: &[DVec3],
    up: Option<[f64; 3]>,
    scale: f64,
) -> WorldFrame {
    let (up, plane, source) = match up {
        Some(u) => (DVec3::from(u).normalize(), None, "--up"),
        None => estimate_up(shots, points),
    };
    let rotation = rotation_to_y(up);
    let cloud: Vec<DVec3> = if points.is_empty() {
        shots.iter().map(|s| s.centre).collect()
    } else {
        points.to_vec()
    };
    let med = |k: usize| {
        let mut v: Vec<f64> = cloud.iter().map(|p| p[k]).collect();
        crate::stats::median(&mut v).unwrap_or(0.0)
    };
    let mid = DVec3::new(med(0), med(1), med(2));
    // The origin: the median, dropped along up onto the plane (or kept at the median).
    let origin = match plane {
        Some(c) => mid - up * (mid - c).dot(up),
        None => mid,
    };
    WorldFrame {
        rotation,
        origin,
        scale,
        up_source: source,
    }
}

/// The dataset camera of a shot in the new world, through the pinhole image `pin`.
pub fn dataset_camera(shot: &Shot, pin: &Pinhole, frame: &WorldFrame) -> Camera {
    let c2w = frame.rotation * shot.rotation;
    let c = frame.point(shot.centre);
    let row = |i: usize| {
        [
            c2w.x_axis[i] as f32,
            c2w.y_axis[i] as f32,
            c2w.z_axis[i] as f32,
            c[i] as f32,
        ]
    };
    Camera {
        transform_matrix: [row(0), row(1), row(2), [0.0, 0.0, 0.0, 1.0]],
        fl_x: pin.fx as f32,
        fl_y: pin.fy as f32,
        cx: pin.cx as f32,
        cy: pin.cy as f32,
        w: pin.width,
        h: pin.height,
    }
}

/// A photo as linear RGB, row-major, with its size. 8- and 16-bit sRGB are decoded with the
/// sRGB curve.
fn read_photo(path: &Path) -> Result<(u32, u32, Vec<[f32; 3]>)> {
    if !path.is_file() {
        return Err(Error::invalid(
            path,
            "file",
            "expected the photo here (the capture names it)",
        ));
    }
    let img = open_image(path)
        .map_err(|e| Error::invalid(path, "file", format!("expected a JPEG or PNG photo: {e}")))?;
    let (w, h) = (img.width(), img.height());
    let rgb = img.to_rgb32f();
    let px = rgb
        .pixels()
        .map(|p| p.0.map(crate::scene::color::srgb_to_linear))
        .collect();
    Ok((w, h, px))
}

/// Decodes an image by its content, not its extension (cameras and tools misname files).
fn open_image(path: &Path) -> std::result::Result<image::DynamicImage, image::ImageError> {
    image::ImageReader::open(path)?
        .with_guessed_format()?
        .decode()
}

fn read_id_mask(path: &Path) -> Result<(u32, u32, Vec<u8>)> {
    if !path.is_file() {
        return Err(Error::invalid(
            path,
            "file",
            "expected this photo's id mask here (--masks holds one per photo: <image name>.png)",
        ));
    }
    let img = open_image(path).map_err(|e| {
        Error::invalid(
            path,
            "file",
            format!("expected an 8-bit PNG of object ids: {e}"),
        )
    })?;
    match img {
        image::DynamicImage::ImageLuma8(m) => Ok((m.width(), m.height(), m.into_raw())),
        other => Err(Error::invalid(
            path,
            "pixel format",
            format!(
                "expected an 8-bit single-channel PNG of object ids, found {:?}",
                other.color()
            ),
        )),
    }
}

/// Bilinear sample of a row-major RGB image at a pixel position (centres at +0.5), clamped
/// at the border.
fn bilinear(img: &[[f32; 3]], w: u32, h: u32, p: [f64; 2]) -> [f32; 3] {
    let x = (p[0] - 0.5).clamp(0.0, w as f64 - 1.0);
    let y = (p[1] - 0.5).clamp(0.0, h as f64 - 1.0);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w as usize - 1), (y0 + 1).min(h as usize - 1));
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let at = |xx: usize, yy: usize| img[yy * w as usize + xx];
    let mut out = [0.0; 3];
    for (c, o) in out.iter_mut().enumerate() {
        let top = at(x0, y0)[c] * (1.0 - fx) + at(x1, y0)[c] * fx;
        let bot = at(x0, y1)[c] * (1.0 - fx) + at(x1, y1)[c] * fx;
        *o = top * (1.0 - fy) + bot * fy;
    }
    out
}

/// Per pixel of a pinhole image, where in the photo it comes from ([`source_map`]).
type SourceMap = Vec<[f64; 2]>;

/// Where in the photo each pixel of the pinhole image `pin` comes from (row-major, pixel
/// positions with centres at +0.5), or None for a pinhole lens, whose photo is copied. Computed
/// once per camera: every photo of it, and its mask and depth, share the map.
fn source_map(lens: &Lens, pin: &Pinhole) -> Option<SourceMap> {
    if lens.is_pinhole() {
        return None;
    }
    let w = pin.width as usize;
    Some(
        (0..w * pin.height as usize)
            .into_par_iter()
            .map(|i| {
                let px = [(i % w) as f64 + 0.5, (i / w) as f64 + 0.5];
                // Inside the photo by construction of `pin` (Lens::pinhole); clamped at the edge.
                lens.source_pixel(pin, px).unwrap_or(px)
            })
            .collect(),
    )
}

/// A photo (or its mask, or its depth) resampled through `map` ([`source_map`]): `sample`
/// reads it at a pixel position; without a map, `direct` copies pixel `i`.
fn resample<T: Copy + Send>(
    map: Option<&[[f64; 2]]>,
    n: usize,
    sample: impl Fn([f64; 2]) -> T + Sync,
    direct: impl Fn(usize) -> T + Sync,
) -> Vec<T> {
    match map {
        Some(m) => m.par_iter().map(|&s| sample(s)).collect(),
        None => (0..n).into_par_iter().map(&direct).collect(),
    }
}

/// A depth image as planar depth in stored units: a 16- or 8-bit single-channel PNG
/// (nerfstudio's millimetres) or an EXR's `Z` (else `Y`, else `R`) channel.
fn read_depth(path: &Path) -> Result<(u32, u32, Vec<f32>)> {
    if !path.is_file() {
        return Err(Error::invalid(
            path,
            "file",
            "expected this photo's depth image here (depth_file_path names it)",
        ));
    }
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"))
    {
        let c = super::exr::read_channels(path)?;
        let plane = ["Z", "Y", "R"]
            .iter()
            .find_map(|n| c.get(n))
            .ok_or_else(|| {
                Error::invalid(
                    path,
                    "channels",
                    "expected a Z (or Y, or R) channel of depth",
                )
            })?;
        return Ok((c.width as u32, c.height as u32, plane.to_vec()));
    }
    let img = open_image(path).map_err(|e| {
        Error::invalid(
            path,
            "file",
            format!("expected a 16-bit PNG or an EXR of depth: {e}"),
        )
    })?;
    let (w, h) = (img.width(), img.height());
    let v = match img {
        image::DynamicImage::ImageLuma16(m) => m.into_raw().into_iter().map(f32::from).collect(),
        image::DynamicImage::ImageLuma8(m) => m.into_raw().into_iter().map(f32::from).collect(),
        other => {
            return Err(Error::invalid(
                path,
                "pixel format",
                format!(
                    "expected a single-channel depth image, found {:?}",
                    other.color()
                ),
            ));
        }
    };
    Ok((w, h, v))
}

/// The relative path a frame's file is written to: `<dir>/<state>/<stem>.<ext>`.
fn out_rel(dir: &str, state: &str, name: &str, ext: &str) -> String {
    let stem = super::file_stem(name).unwrap_or_default();
    format!("{dir}/{state}/{stem}.{ext}")
}

/// The sparse depth of one photo: each SfM point it sees, in the dataset's world, projected
/// through its dataset camera; `Z` its planar depth in metres at the pixel it lands in (the
/// nearest when two land in one), `C` its confidence `1 / (1 + e²)` for a mean reprojection
/// error of `e` pixels (COLMAP's `ERROR`: 1 for an exact point, ½ at one pixel). Both 0 where
/// no point lands. This is the paper's depth term's `C_v` for a capture without depth sensors.
fn sparse_depth(
    camera: &Camera,
    seen: &[usize],
    capture: &Capture,
    frame: &WorldFrame,
) -> (Vec<f32>, Vec<f32>) {
    let (w, h) = (camera.w as usize, camera.h as usize);
    let (mut z, mut c) = (vec![0.0f32; w * h], vec![0.0f32; w * h]);
    for &p in seen {
        let x = frame.point(capture.points[p]);
        let Some((px, depth)) = camera.project([x.x as f32, x.y as f32, x.z as f32]) else {
            continue;
        };
        if !(px[0] >= 0.0 && px[1] >= 0.0 && (px[0] as usize) < w && (px[1] as usize) < h) {
            continue;
        }
        let i = px[1] as usize * w + px[0] as usize;
        if z[i] == 0.0 || depth < z[i] {
            let e = capture.point_errors[p];
            z[i] = depth;
            c[i] = (1.0 / (1.0 + e * e)) as f32;
        }
    }
    (z, c)
}

/// Reads the `--states` file: a JSON object of photo name to state name.
fn read_state_map(file: &Path) -> Result<(PathBuf, BTreeMap<String, String>)> {
    let bytes = std::fs::read(file).map_err(|e| Error::io(file, e))?;
    let m: BTreeMap<String, String> = serde_json::from_slice(&bytes).map_err(|e| {
        Error::invalid(
            file,
            "states",
            format!("expected a JSON object of photo name to state name: {e}"),
        )
    })?;
    Ok((file.to_path_buf(), m))
}

/// `lightfuse import colmap`.
pub fn import_colmap(a: &ColmapImport) -> Result<ImportSummary> {
    write_dataset(colmap_capture(a)?, &a.options)
}

/// `lightfuse import nerfstudio`.
pub fn import_nerfstudio(a: &NerfstudioImport) -> Result<ImportSummary> {
    if !(a.depth_unit_scale.is_finite() && a.depth_unit_scale > 0.0) {
        return Err(Error::Usage(format!(
            "--depth-unit-scale: expected metres per stored unit > 0, found {}",
            a.depth_unit_scale
        )));
    }
    write_dataset(nerfstudio_capture(a)?, &a.options)
}

/// The scale from two marked points (`--scale-points`) and what `import.json` says of it.
fn measured_scale(capture: &Capture, m: &ScalePoints) -> Result<(f64, String)> {
    if !(m.metres.is_finite() && m.metres > 0.0) {
        return Err(Error::Usage(format!(
            "--scale-points: expected the points' distance in metres > 0, found {}",
            m.metres
        )));
    }
    let resolve = |p: &MarkedPoint| -> Result<DVec3> {
        match *p {
            MarkedPoint::Source(x) => Ok(DVec3::from(x)),
            MarkedPoint::Point(id) => match &capture.tracks {
                None => Err(Error::Usage(format!(
                    "--scale-points: point:{id} names a COLMAP 3D point, and a {} capture has none; give the point as X,Y,Z in its frame",
                    capture.source
                ))),
                Some((file, _)) => capture
                    .point_ids
                    .iter()
                    .position(|&i| i == id)
                    .map(|k| capture.points[k])
                    .ok_or_else(|| {
                        Error::invalid(
                            file,
                            "--scale-points",
                            format!("expected a 3D point with id {id}, found none"),
                        )
                    }),
            },
        }
    };
    let (a, b) = (resolve(&m.a)?, resolve(&m.b)?);
    let d = a.distance(b);
    if d.is_nan() || d <= 1e-12 * a.length().max(b.length()).max(1.0) {
        return Err(Error::Usage(format!(
            "--scale-points: the two points are the same ({a:?}); expected two points apart"
        )));
    }
    Ok((
        m.metres / d,
        format!(
            "--scale-points: {:?} and {:?}, {d} source units apart, {} m",
            m.a, m.b, m.metres
        ),
    ))
}

/// What every source shares: states, the world frame, the pixels, `dataset.json` (written last,
/// so an interrupted import leaves no dataset) and `import.json`.
fn write_dataset(capture: Capture, o: &ImportOptions) -> Result<ImportSummary> {
    if let Some(u) = o.up {
        if !(u.iter().all(|c| c.is_finite()) && u.iter().any(|&c| c != 0.0)) {
            return Err(Error::Usage(format!(
                "--up: expected a non-zero direction X,Y,Z, found {u:?}"
            )));
        }
    }
    if let Some(s) = o.scale {
        if !(s.is_finite() && s > 0.0) {
            return Err(Error::Usage(format!(
                "--scale: expected metres per source unit > 0, found {s}"
            )));
        }
    }
    let (scale, scale_source) = match (&o.scale_points, o.scale) {
        (Some(m), _) => measured_scale(&capture, m)?,
        (None, Some(s)) => (s, "--scale".to_string()),
        (None, None) => (1.0, "none given: source units taken as metres".to_string()),
    };
    for shot in &capture.shots {
        if let Some(why) = shot.lens.unsupported() {
            return Err(Error::invalid(
                &shot.lens_in.0,
                format!("{}.model", shot.lens_in.1),
                why,
            ));
        }
    }
    // A new or empty folder, or what an interrupted import left (images/, masks/, depth/,
    // sparse_depth/ and no dataset.json yet): nothing else is ever overwritten.
    if let Ok(it) = std::fs::read_dir(&o.out) {
        let ours = |n: &str| matches!(n, "images" | "masks" | "depth" | "sparse_depth");
        if let Some(e) = it
            .filter_map(|e| e.ok())
            .find(|e| !ours(&e.file_name().to_string_lossy()))
        {
            return Err(Error::invalid(
                &o.out,
                "output folder",
                format!("expected a new or empty folder, found {:?} in it (nothing here is overwritten)", e.file_name()),
            ));
        }
    }
    let map = o.states.as_deref().map(read_state_map).transpose()?;
    let states: Vec<String> = capture
        .shots
        .iter()
        .map(|s| state_of(map.as_ref(), s))
        .collect::<Result<_>>()?;
    let names: BTreeSet<String> = states.iter().cloned().collect();
    for t in &o.test_states {
        if !names.contains(t) {
            return Err(Error::Usage(format!(
                "--test-states: no state {t:?} in the capture; its states are {}",
                names.iter().cloned().collect::<Vec<_>>().join(", ")
            )));
        }
    }
    if names.iter().all(|n| o.test_states.contains(n)) {
        return Err(Error::Usage(
            "--test-states: every state is held out; at least one must train".into(),
        ));
    }
    if let Some((file, tracks)) = &capture.tracks {
        check_one_world(file, tracks, &states)?;
    }
    // Two photos written to one file would lose one of them.
    let mut taken: BTreeMap<String, &str> = BTreeMap::new();
    for (shot, st) in capture.shots.iter().zip(&states) {
        let rel = out_rel("images", st, &shot.name, "exr");
        if let Some(other) = taken.insert(rel.clone(), &shot.name) {
            return Err(Error::invalid(
                &shot.named_in.0,
                format!("{}.name", shot.named_in.1),
                format!(
                    "{:?} and {other:?} are both state {st:?}'s {rel}: rename one",
                    shot.name
                ),
            ));
        }
    }
    let frame = world_frame(&capture.shots, &capture.points, o.up, scale);
    // Each shot's points (index into `capture.points`), for its sparse depth.
    let mut seen_by: Vec<Vec<usize>> = vec![Vec::new(); capture.shots.len()];
    if let Some((_, tracks)) = &capture.tracks {
        for (p, track) in tracks.iter().enumerate() {
            for &k in track {
                seen_by[k].push(p);
            }
        }
    }
    let progress = crate::progress::Progress::new(o.quiet, capture.shots.len() as u64, "import");
    let mut frames: BTreeMap<String, Vec<(String, Frame)>> = BTreeMap::new();
    let mut ids: BTreeSet<u8> = BTreeSet::new();
    let mut cameras = serde_json::Map::new();
    let mut files = super::AtomicFiles::new();
    // One pinhole camera and source map per distinct lens (photos of one camera share them).
    let mut lenses: Vec<(Lens, Pinhole, Option<SourceMap>)> = Vec::new();
    for (k, (shot, st)) in capture.shots.iter().zip(&states).enumerate() {
        let lens = &shot.lens;
        let at_lens = match lenses.iter().position(|(l, _, _)| l == lens) {
            Some(i) => i,
            None => {
                let pin = lens.pinhole().ok_or_else(|| {
                    Error::invalid(
                        &shot.lens_in.0,
                        format!("{}.params", shot.lens_in.1),
                        "expected a lens whose border can be undistorted (this distortion folds \
                         over within the image)",
                    )
                })?;
                let map = source_map(lens, &pin);
                lenses.push((lens.clone(), pin, map));
                lenses.len() - 1
            }
        };
        let (_, pin, map) = &lenses[at_lens];
        let (pin, map) = (*pin, map.as_deref());
        let (w, h, px) = read_photo(&shot.photo)?;
        if (w, h) != (lens.width, lens.height) {
            return Err(Error::invalid(
                &shot.photo,
                "size",
                format!(
                    "expected {}x{} ({} of {}), found {w}x{h}",
                    lens.width,
                    lens.height,
                    shot.lens_in.1,
                    shot.lens_in.0.display()
                ),
            ));
        }
        let at = |s: [f64; 2]| {
            let x = (s[0].floor().max(0.0) as usize).min(w as usize - 1);
            let y = (s[1].floor().max(0.0) as usize).min(h as usize - 1);
            y * w as usize + x
        };
        let rgb = resample(map, px.len(), |s| bilinear(&px, w, h, s), |i| px[i]);
        let file_path = out_rel("images", st, &shot.name, "exr");
        let planes = |names: &[&str], v: Vec<Vec<f32>>| super::exr::Channels {
            width: w as usize,
            height: h as usize,
            channels: names.iter().map(|n| n.to_string()).zip(v).collect(),
        };
        let rgb_planes = (0..3).map(|c| rgb.iter().map(|p| p[c]).collect()).collect();
        super::exr::write_channels(
            &planes(&["R", "G", "B"], rgb_planes),
            &o.out.join(&file_path),
        )?;
        let mut mask_path = None;
        if let Some(mp) = &shot.mask {
            let (mw, mh, m) = read_id_mask(mp)?;
            if (mw, mh) != (w, h) {
                return Err(Error::invalid(
                    mp,
                    "size",
                    format!("expected {w}x{h}, the photo's size, found {mw}x{mh}"),
                ));
            }
            let out = resample(map, px.len(), |s| m[at(s)], |i| m[i]);
            ids.extend(out.iter().copied().filter(|&v| v != 0));
            let rel = out_rel("masks", st, &shot.name, "png");
            let mut png = std::io::Cursor::new(Vec::new());
            image::GrayImage::from_raw(w, h, out)
                .expect("mask size")
                .write_to(&mut png, image::ImageFormat::Png)
                .map_err(|e| Error::invalid(o.out.join(&rel), "file", e.to_string()))?;
            files.write(&o.out.join(&rel), &png.into_inner())?;
            mask_path = Some(rel);
        }
        let mut depth_file_path = None;
        if let Some(dp) = &shot.depth {
            let (dw, dh, d) = read_depth(dp)?;
            if (dw, dh) != (w, h) {
                return Err(Error::invalid(
                    dp,
                    "size",
                    format!("expected {w}x{h}, the photo's size, found {dw}x{dh}"),
                ));
            }
            // Planar depth is the point's distance along the optical axis, which resampling
            // into the pinhole image does not change; only the units do.
            let k = (capture.depth_unit_scale * scale) as f32;
            let out: Vec<f32> = resample(map, px.len(), |s| d[at(s)], |i| d[i])
                .into_iter()
                .map(|z| z * k)
                .collect();
            if let Some((i, z)) = out
                .iter()
                .enumerate()
                .find(|(_, z)| !(z.is_finite() && **z >= 0.0))
            {
                return Err(Error::invalid(
                    dp,
                    "depth",
                    format!("expected finite depth >= 0, found {z} at pixel {i}"),
                ));
            }
            let rel = out_rel("depth", st, &shot.name, "exr");
            super::exr::write_channels(&planes(&["Z"], vec![out]), &o.out.join(&rel))?;
            depth_file_path = Some(rel);
        }
        let camera = dataset_camera(shot, &pin, &frame);
        let mut sparse_depth_file_path = None;
        if capture.tracks.is_some() {
            let (z, c) = sparse_depth(&camera, &seen_by[k], &capture, &frame);
            let rel = out_rel("sparse_depth", st, &shot.name, "exr");
            super::exr::write_channels(&planes(&["C", "Z"], vec![c, z]), &o.out.join(&rel))?;
            sparse_depth_file_path = Some(rel);
        }
        cameras.insert(
            shot.name.clone(),
            serde_json::json!({
                "model": lens.model.name(), "params": lens.params, "width": lens.width, "height": lens.height,
                "resampled": !lens.is_pinhole(),
            }),
        );
        frames.entry(st.clone()).or_default().push((
            shot.name.clone(),
            Frame {
                file_path,
                depth_file_path,
                normal_file_path: None,
                sparse_depth_file_path,
                mask_path,
                albedo_file_path: None,
                camera,
            },
        ));
        progress.inc(1);
    }
    files.commit()?;
    drop(progress);

    let mut states_out = Vec::new();
    for (name, mut fr) in frames {
        fr.sort_by(|a, b| a.0.cmp(&b.0));
        let split = if o.test_states.contains(&name) {
            "test"
        } else {
            "train"
        };
        states_out.push(DatasetState {
            name,
            split: split.into(),
            environment: None,
            environment_source: None,
            object_poses: BTreeMap::new(),
            frames: fr.into_iter().map(|(_, f)| f).collect(),
            relight: Vec::new(),
        });
    }
    // Training states first: the first is the reference state of object poses.
    states_out.sort_by_key(|s| s.split != "train");
    let objects: Vec<DatasetObject> = ids
        .iter()
        .map(|&id| DatasetObject {
            id: id as u32,
            name: format!("object_{id}"),
            reference_pose: None,
            symmetries: Vec::new(),
            material: None,
        })
        .collect();
    let dataset = serde_json::json!({"format": DATASET_FORMAT, "up": "+Y", "objects": objects, "states": states_out});
    let r = frame.rotation;
    let provenance = serde_json::json!({
        "format": "lightfuse-import/1",
        "source": capture.source,
        "from": capture.provenance,
        "world_from_source": {
            "note": "x_dataset = scale * rotation * (x_source - origin)",
            "scale": frame.scale,
            "scale_source": scale_source,
            "rotation": [r.row(0).to_array(), r.row(1).to_array(), r.row(2).to_array()],
            "origin": frame.origin.to_array(),
            "up_source": frame.up_source,
        },
        "cameras": cameras,
    });
    let summary = ImportSummary {
        dataset: o.out.join("dataset.json"),
        states: states_out
            .iter()
            .map(|s| (s.name.clone(), s.split.clone(), s.frames.len()))
            .collect(),
        objects: ids.into_iter().collect(),
        undistorted: capture
            .shots
            .iter()
            .filter(|s| !s.lens.is_pinhole())
            .count(),
        frame,
    };
    let mut files = super::AtomicFiles::new();
    let pretty = |v: &serde_json::Value| serde_json::to_vec_pretty(v).expect("json");
    files.write(&o.out.join("import.json"), &pretty(&provenance))?;
    files.write(&o.out.join("dataset.json"), &pretty(&dataset))?;
    files.commit()?;
    Ok(summary)
}
