//! Optimisation building blocks for the three training stages (docs/design.md §1; paper §"Training and
//! Inference"): Adam over parameter groups with learning-rate schedules, and the image-space
//! losses of eqs. reconstruction-objective, geometry-objective and training-objectives, each
//! returning its value and its gradient with respect to the rendered buffers.
//!
//! Everything works on plain row-major buffers as the renderers produce them: colour
//! `[[f32; 3]]`, alpha/depth `[f32]`, world normals `[[f32; 3]]`, with the image size passed
//! separately where a loss looks at neighbours. Lengths that disagree are programming errors
//! and panic with a message; data from files (checkpoints) is checked by
//! [`Adam::validate`] and [`Adam::expect_group`] and reported as [`crate::Error::invalid`].

pub mod adam;
pub mod geometry;
pub mod loss;
pub mod pyramid;
pub mod ssim;

pub use adam::{Adam, Group, Schedule};
pub use geometry::{depth_normal_loss, depth_normals, DepthNormalLoss};
pub use loss::{
    alpha_coverage, depth_l1, display_encode, env_tv, l1, normal_loss, rgb_loss, rgb_loss_display,
    scale_regularization, LAMBDA_DSSIM,
};
pub use ssim::{d_ssim, ssim};

/// The logistic function, the activation of every parameter kept in (0, 1) as a logit.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// The inverse of [`sigmoid`], clamped to [1e-4, 1 − 1e-4] so that 0 and 1 stay finite.
#[inline]
pub fn logit(a: f32) -> f32 {
    let a = a.clamp(1e-4, 1.0 - 1e-4);
    (a / (1.0 - a)).ln()
}

/// A loss value and its gradient with respect to one input buffer (same layout as the input).
#[derive(Clone, Debug, PartialEq)]
pub struct Loss<G> {
    pub value: f32,
    pub grad: G,
}

/// A weighted loss: value, gradient with respect to the rendered buffer, and gradient with
/// respect to the per-pixel weights (confidence, mask or alpha), for callers whose weights are
/// themselves rendered or learned.
#[derive(Clone, Debug, PartialEq)]
pub struct WeightedLoss<G> {
    pub value: f32,
    pub grad: G,
    pub grad_weight: Vec<f32>,
}
