//! Stage 1, reconstruct (paper §"Interactive Scene Reconstruction").

pub mod completion;
pub mod maxflow;
pub mod segment;
pub mod train;
