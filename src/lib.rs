//! LightFuse: relightable, rearrangeable scenes of 2D Gaussian surfels with physically based
//! materials, reconstructed from multi-state captures. See `docs/design.md` and
//! `docs/formats.md` for the data flow, the conventions and the file formats.

pub mod error;
pub mod eval;
pub mod io;
pub mod kernel;
pub mod optim;
pub mod progress;
pub mod scene;
pub mod shade;
pub mod spatial;
pub mod splat;
pub mod stages;
pub mod stats;
pub mod trace;

pub use error::{Error, Result};
