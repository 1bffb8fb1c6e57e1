//! Stage 2: ray-tracing-oriented geometry refinement (paper §"Ray-Tracing-Oriented Geometry
//! Optimization", eq. geometry-objective). Stage 1 fits surfels for splatting; path tracing
//! shoots shadow and secondary rays from where no camera stood, and there splat-trained surfels
//! leak light through holes, occlude with oversized discs and bend rays off tilted normals. This
//! stage refines the shared geometry with the same plane intersection and compositing the path
//! tracer uses ([`crate::trace`]), supervised by the captures' depth, normals and coverage across
//! every training state. No RGB term: appearance is stage 3's.
//!
//! [`train`] is the loop, [`run`] reads stage 1's scene and writes `refined.glb` with a report
//! that measures the geometry by ray tracing before and after ([`crate::eval::geometry`]).

pub mod run;
pub mod train;

pub use run::{refine, Options, Report};
pub use train::{Settings, Switches};
