//! The paper's stages, each a plain function of files (docs/design.md §4).

pub mod common;
pub mod invert;
pub mod pipeline;
pub mod reconstruct;
pub mod refine;
