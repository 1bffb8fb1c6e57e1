//! Evaluation against ground truth: image and depth metrics (reports come later).

pub mod metrics;

pub use metrics::{depth_error, psnr, psnr_srgb, srgb_encode, ssim, ssim_srgb, DepthError};
