//! Evaluation against ground truth: image and depth metrics, symmetry-aware object pose error,
//! stage 3's lighting and material figures; `lightfuse evaluate` and its report page.

pub mod geometry;
pub mod html;
pub mod labels;
pub mod lighting;
pub mod metrics;
pub mod pose;
pub mod relight;
pub mod report;
pub mod shadows;
pub mod stage1;
pub mod stage3;
pub mod tables;

pub use metrics::{depth_error, psnr, psnr_srgb, ssim, ssim_srgb, DepthError};
