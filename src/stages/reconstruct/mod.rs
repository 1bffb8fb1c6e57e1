//! Stage 1, reference reconstruction (paper §"Interactive Scene Reconstruction").

pub mod init;
pub mod register;
