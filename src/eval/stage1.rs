//! Stage 1's own figures (`report.json`): the reconstruction rendered into the views it held
//! out and the views it trained on, against the captures (PSNR over the pixels the capture saw
//! a surface in, depth error, a comparison image each), and each object's estimated pose
//! against the dataset's truth, forgiving declared symmetries (evaluation only).

use crate::error::Result;
use crate::eval::pose::pose_error;
use crate::eval::report::{covered_psnr_srgb, depth_errors, save_comparison, ObjectPoseError};
use crate::io::dataset::{Dataset, Observation};
use crate::io::work::{stage1_view_name, PoseSteps, WorkDir};
use crate::scene::{Camera, Rigid};
use crate::splat::SplatImage;
use crate::stats::median;
use glam::Vec3;
use serde::Serialize;

/// One held-out view's figures.
#[derive(Clone, Debug, Serialize)]
pub struct HeldOutView {
    pub state: String,
    pub view: usize,
    pub psnr_srgb: f64,
    pub median_depth_error_m: f64,
    /// Capture | render | 4 × |difference|, sRGB, covered pixels only.
    pub image: String,
}

/// What [`view_figures`] measures.
pub struct ViewFigures {
    pub heldout: Vec<HeldOutView>,
    /// Mean over the held-out views.
    pub heldout_psnr_srgb: f64,
    /// Mean over the training views: the gap to the held-out figure is how much is fitted
    /// rather than learned.
    pub train_psnr_srgb: f64,
    /// Median depth error over every held-out pixel with a reference depth.
    pub median_depth_error_m: f64,
    /// The diagonal of the training captures' points' bounds.
    pub extent_m: f64,
}

/// `render(j, camera)` (the reconstruction in training state j) against every held-out view
/// (`held[j]`) and training view (`train[j]`) of training state `train_states[j]`; writes the
/// comparison images into `work` (`heldout/`, `train/`).
pub fn view_figures(
    render: &dyn Fn(usize, &Camera) -> SplatImage,
    dataset: &Dataset,
    train_states: &[usize],
    train: &[Vec<Observation>],
    held: &[Vec<Observation>],
    work: &WorkDir,
) -> Result<ViewFigures> {
    // Held-out views: PSNR over covered pixels, depth error, a comparison image each.
    let mut psnrs = Vec::new();
    let mut depth_err: Vec<f64> = Vec::new();
    let mut heldout = Vec::new();
    for (j, views) in held.iter().enumerate() {
        let state = &dataset.states[train_states[j]].name;
        for o in views {
            let img = render(j, &o.camera);
            let mut view_depth = depth_errors(&img.depth, &img.alpha, &o.depth);
            if view_depth.is_empty() {
                continue;
            }
            let psnr = covered_psnr_srgb(&img.color, &o.rgb, &o.depth);
            psnrs.push(psnr);
            let name = stage1_view_name(true, state, o.view);
            save_comparison(
                &img.color,
                &o.rgb,
                &o.depth,
                o.camera.w,
                o.camera.h,
                &work.root().join(&name),
            )?;
            depth_err.extend(&view_depth);
            heldout.push(HeldOutView {
                state: state.clone(),
                view: o.view,
                psnr_srgb: psnr,
                median_depth_error_m: median(&mut view_depth).unwrap_or(f64::NAN),
                image: name,
            });
        }
    }
    // Training views, for the gap between fitting and generalising (images in `train/`).
    let mut train_psnrs = Vec::new();
    for (j, views) in train.iter().enumerate() {
        let state = &dataset.states[train_states[j]].name;
        for o in views {
            let img = render(j, &o.camera);
            train_psnrs.push(covered_psnr_srgb(&img.color, &o.rgb, &o.depth));
            let path = work.stage1_view(false, state, o.view);
            save_comparison(&img.color, &o.rgb, &o.depth, o.camera.w, o.camera.h, &path)?;
        }
    }
    let median = median(&mut depth_err).unwrap_or(f64::NAN);
    // Scene extent from the training captures' points.
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for views in train {
        for o in views {
            for (i, &z) in o.depth.iter().enumerate() {
                if z > 0.0 {
                    let (x, y) = (i % o.camera.w as usize, i / o.camera.w as usize);
                    let p = Vec3::from_array(o.camera.pixel_to_world(
                        x as f32 + 0.5,
                        y as f32 + 0.5,
                        z,
                    ));
                    lo = lo.min(p);
                    hi = hi.max(p);
                }
            }
        }
    }
    let extent_m = (hi - lo).length() as f64;
    Ok(ViewFigures {
        heldout_psnr_srgb: psnrs.iter().sum::<f64>() / psnrs.len().max(1) as f64,
        train_psnr_srgb: train_psnrs.iter().sum::<f64>() / train_psnrs.len().max(1) as f64,
        heldout,
        median_depth_error_m: median,
        extent_m,
    })
}

/// Each object's pose in every training state but the reference one (`poses[j][o]`) against
/// the dataset's, relative to the reference state; also each recorded step's (`steps`, from
/// `poses.json`). Measured in the object's frame, or at `centroid(o)` (world) where the dataset
/// gives none.
pub fn pose_errors(
    dataset: &Dataset,
    train_states: &[usize],
    poses: &[Vec<Rigid>],
    centroid: &dyn Fn(usize) -> Vec3,
    steps: Option<&PoseSteps>,
) -> Result<Vec<ObjectPoseError>> {
    let mut pose_errors = Vec::new();
    let ref_k = train_states[0];
    for (j, &k) in train_states.iter().enumerate().skip(1) {
        for (o, obj) in dataset.objects.iter().enumerate() {
            let gt = dataset
                .object_pose(k, &obj.name)?
                .compose(&dataset.object_pose(ref_k, &obj.name)?.inverse());
            let frame = match obj.reference_pose {
                Some(_) => dataset.object_frame(o)?,
                None => Rigid {
                    translation: centroid(o).to_array(),
                    ..Rigid::IDENTITY
                },
            };
            let error = |pose: &Rigid| pose_error(&gt, pose, &frame, &obj.symmetries);
            pose_errors.push(ObjectPoseError {
                state: dataset.states[k].name.clone(),
                object: obj.name.clone(),
                error: error(&poses[j][o]),
                registered: steps.and_then(|s| s.registered[j][o].as_ref()).map(error),
                aligned: steps.map(|s| error(&s.aligned[j][o])),
                polished: steps.map(|s| error(&s.polished[j][o])),
                turned: steps.map(|s| error(&s.turned[j][o])),
            });
        }
    }
    Ok(pose_errors)
}
