//! Shading building blocks of the one-bounce path tracer (paper § Differentiable one-bounce
//! path tracing, eqs. rendering-equation and path-estimator):
//!
//! - [`brdf`]: the metallic-roughness BRDF (Lambert + GGX, glTF's reference model) with
//!   `eval_f` / `eval_f_cos`, `sample` from a cosine / GGX-VNDF mixture and its `pdf`;
//! - [`envmap`]: lat-long environment lookups mapped exactly as Cycles maps a World
//!   Environment Texture (after the axis change of docs/design.md §2, with the state's rotation about
//!   +Y), and their importance sampling;
//! - [`render`]: the estimator over every pixel of a camera, into an image's channels;
//! - [`replay`]: path replay, a path sample's decisions and terms, and their adjoint (PRB);
//! - [`sobol`]: the replayable Owen-scrambled Sobol sampler that path replay needs.
//!
//! Each sampler comes with the density it draws from; `tests/shade.rs` checks that the densities
//! integrate to one, match histograms of the samples, and agree with the samples' weights.

pub mod brdf;
pub mod denoise;
pub mod envmap;
pub mod estimator;
pub mod render;
pub mod replay;
pub mod sobol;

pub use brdf::Sample;
pub use envmap::{EnvMap, EnvSample};
pub use sobol::Sampler;
