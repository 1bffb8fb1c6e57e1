//! Stage 1, reconstruct (paper §"Interactive Scene Reconstruction"): initialisation from RGB-D
//! ([`init`]), object poses per state ([`poses`], from [`register`] and [`align`]), the background/object graph cut
//! ([`segment`], [`maxflow`]), completion (eq. completion-mask, [`completion`]), the training
//! loop ([`train`]), the removal of object surfels grown beneath their supports ([`support`]) and
//! the stage as a function of files ([`run`]); [`align`] estimates object
//! poses by rendering, an alternative to [`register`].

pub mod align;
pub mod completion;
pub mod init;
pub mod maxflow;
pub mod poses;
pub mod register;
pub mod run;
pub mod segment;
pub mod support;
pub mod train;
