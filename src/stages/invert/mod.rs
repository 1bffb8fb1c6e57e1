//! Stage 3: multi-state inverse rendering (paper § "Multi-State Inverse Rendering", eqs.
//! rendering-equation, path-estimator and training-objectives). With the geometry of stage 2
//! and the object poses of stage 1 fixed, it separates what belongs to the surfaces (base
//! colour, metallic, roughness, shared by every state) from what belongs to each capture (its
//! HDR environment) by differentiating the one-bounce path tracer that later relights the
//! scene, with path replay backpropagation ([`crate::shade::replay`]).
//!
//! [`train`] is the loop over [`cache`]'s primary records, [`run`] reads the refined scene and writes `relightable.glb` /
//! `relightable.usda` with a report.

pub mod cache;
pub mod hypotheses;
pub mod lightfit;
pub mod prior;
pub mod run;
pub mod train;

pub use run::{invert, Options, Report};
pub use train::{Settings, SppSchedule};
