//! HDR denoising of path-traced images with Intel Open Image Denoise (OIDN), guided by albedo
//! and normal images.
//!
//! The paper's evaluation denoised its renders with OptiX's HDR denoiser and albedo + normal
//! guides. OptiX needs an NVIDIA GPU; OIDN's `RT` filter is the CPU equivalent (a U-Net trained
//! on path-traced images, with the same pair of guides) and is a real dependency here: the
//! [`oidn`](https://docs.rs/oidn) crate over the OIDN 2.5.1 library that the venv's `pyoidn`
//! wheel ships (blender/requirements.txt; see build.rs for how it is found and linked). It is
//! behind the cargo feature `denoise`, which `bash scripts/setup.sh` builds with; without it
//! [`denoise_hdr`] returns an error and [`available`] is false.
//!
//! What [`denoise_hdr`] sets up: the `RT` filter with `hdr = true`, default quality (high), on
//! OIDN's CPU device with its default thread count (every core).
//!
//! - `color`: scene-linear radiance (the renderer's `R, G, B`), any non-negative range. HDR mode
//!   is for exactly this: OIDN scales the input by its own exposure estimate (auto
//!   `inputScale`), so values in physical units are fine and must not be tone-mapped or
//!   sRGB-encoded first. Non-finite values are rejected: OIDN would zero a NaN, but a single
//!   infinite pixel ruins the whole image through that exposure estimate.
//! - `albedo`: the first-hit surface colour in [0, 1] (the renderer's `albedo.R/G/B`, the base
//!   colour).
//! - `normal`: the first-hit shading normal, world or view space, components in [-1, 1] (unit
//!   length not required; `N.X/Y/Z`). Where the camera ray hits nothing the renderer's zero
//!   albedo and normal are valid inputs.
//!
//! # `cleanAux` stays off
//!
//! OIDN has two sets of weights for guided denoising: `cleanAux = false` (the default; trained
//! with guides that may be noisy, so it leans on the colour where the guides disagree with it)
//! and `cleanAux = true` (guides taken as exact, which keeps more detail). Neither prefilters
//! the guides; OIDN's prefiltering is a separate pass the caller would run on them first.
//! Our guides carry no Monte Carlo noise (they are the record of the ray through the pixel
//! *centre*), but they are aliased: the colour averages jittered rays over the pixel, so along
//! a silhouette or a material edge the colour has a partial-coverage blend while the guides
//! jump by a whole pixel. Measured with OIDN 2.5.1 on a synthetic 128×96 image (an
//! albedo/normal edge slanted 0.3 px per row, colour from 4 or 16 jittered samples, guides from
//! the centre): `cleanAux = true` cut the overall error 1.4–1.7× but raised it 1.5–2.2× within
//! 3 px of the edge (it draws the guides' staircase into the result); with the edge on a pixel
//! boundary (no aliasing) `true` was better everywhere. Staircased edges are the more visible
//! failure and real edges are not pixel-aligned, so we keep `cleanAux = false`. (The `oidn` crate's `clean_aux` setter
//! could not change it anyway: it sets a parameter named `clean_aux`, which OIDN 2.5 ignores as
//! unknown — its name is `cleanAux`.) Guides averaged over the same jittered samples as the
//! colour would match it at edges; with such guides `cleanAux = true` is worth measuring again.

use crate::error::{Error, Result};
use crate::shade::render::Aovs;

/// The albedo and normal guides of one path-traced image, from its pixel-centre records.
pub struct Guides {
    pub albedo: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
}

impl Guides {
    /// Guides for an image rendered from the records `aovs` over `background` (the environment
    /// along each pixel's centre ray), with every base colour multiplied by `base_color_scale`
    /// and clamped to 1 (as [`crate::shade::render::Primaries::shade`] renders it):
    /// - albedo = α · base colour + (1 − α) · background clamped to [0, 1], where α is the
    ///   pixel's mean sample coverage: where the camera sees the environment the "albedo" is
    ///   the environment (as Cycles' denoising albedo, so OIDN keeps its detail), and a
    ///   silhouette pixel gets the same blend as its colour;
    /// - normal = the unit world normal of the record, zero where nothing is hit (OIDN's
    ///   "no surface").
    pub fn new(aovs: &Aovs, background: &[[f32; 3]], base_color_scale: &[f32; 3]) -> Guides {
        let albedo = (0..aovs.alpha.len())
            .map(|i| {
                let a = aovs.alpha[i].clamp(0.0, 1.0);
                [0, 1, 2].map(|c| {
                    a * (aovs.albedo[i][c] * base_color_scale[c]).clamp(0.0, 1.0)
                        + (1.0 - a) * background[i][c].clamp(0.0, 1.0)
                })
            })
            .collect();
        Guides {
            albedo,
            normal: aovs.normal.clone(),
        }
    }
}

/// Denoises an image rendered from the records `aovs` over `background` (the environment along
/// each pixel centre's ray, [`crate::shade::render::environment_image`]), with base colours
/// scaled by `base_color_scale` as it was rendered: [`denoise_hdr`] with [`Guides::new`], then
/// every pixel none of whose samples hit a surface (mean coverage 0) gets its rendered value
/// back. Those pixels are the environment seen through the pixel filter, nearly free of noise;
/// OIDN, which has no guide for the environment's detail, only softens it (measured on a
/// blocky random environment: background MSE against 256 spp 5.5x *higher* after OIDN, while
/// covered pixels gain 11x). OIDN still sees the whole image, so silhouettes keep their context.
pub fn denoise_render(
    color: &[[f32; 3]],
    aovs: &Aovs,
    background: &[[f32; 3]],
    base_color_scale: &[f32; 3],
    width: usize,
    height: usize,
) -> Result<Vec<[f32; 3]>> {
    if aovs.alpha.len() != color.len() || background.len() != color.len() {
        return Err(Error::Usage(format!(
            "denoise: {} pixels of colour, {} of coverage, {} of background",
            color.len(),
            aovs.alpha.len(),
            background.len()
        )));
    }
    let g = Guides::new(aovs, background, base_color_scale);
    let mut out = denoise_hdr(color, &g.albedo, &g.normal, width, height)?;
    for ((o, c), &a) in out.iter_mut().zip(color).zip(&aovs.alpha) {
        if a <= 0.0 {
            *o = *c;
        }
    }
    Ok(out)
}

/// True when this build has the `denoise` feature (Open Image Denoise linked in), so
/// [`denoise_hdr`] can work.
pub fn available() -> bool {
    cfg!(feature = "denoise")
}

/// Ok when this build can denoise; otherwise the error a command that was asked to denoise
/// gives before doing any work: what is missing, how to get it, and `alternative` (e.g. "or
/// pass --no-denoise"), if any.
pub fn require(alternative: &str) -> Result<()> {
    if available() {
        return Ok(());
    }
    Err(Error::Usage(format!(
        "denoising needs Open Image Denoise, but this lightfuse was built without the `denoise` \
         feature: `bash scripts/setup.sh` installs the library and builds with it (by hand: \
         OIDN_DIR=<venv>/lib/python3.X/site-packages/pyoidn/oidn cargo build --release \
         --features denoise){}{alternative}",
        if alternative.is_empty() { "" } else { "; " }
    )))
}

/// Denoises a path-traced HDR image (`width × height` pixels, row-major, scene-linear RGB) with
/// OIDN's `RT` filter in HDR mode, guided by `albedo` (in [0, 1]) and `normal` (in [-1, 1],
/// world or view space); see the [module documentation](self) for what the inputs must be and
/// why `cleanAux` is off. Returns the denoised image in the same layout.
///
/// Errors: a slice whose length is not `width · height`, an empty image, non-finite colour,
/// a failure inside OIDN (with OIDN's message), or a build without the `denoise` feature.
pub fn denoise_hdr(
    color: &[[f32; 3]],
    albedo: &[[f32; 3]],
    normal: &[[f32; 3]],
    width: usize,
    height: usize,
) -> Result<Vec<[f32; 3]>> {
    check_inputs(color, albedo, normal, width, height)?;
    #[cfg(feature = "denoise")]
    {
        oidn_rt(color, albedo, normal, width, height).map_err(|e| Error::External {
            library: "Open Image Denoise",
            message: e.to_string(),
        })
    }
    #[cfg(not(feature = "denoise"))]
    {
        require("").map(|()| Vec::new())
    }
}

fn check_inputs(
    color: &[[f32; 3]],
    albedo: &[[f32; 3]],
    normal: &[[f32; 3]],
    width: usize,
    height: usize,
) -> Result<()> {
    let n = width
        .checked_mul(height)
        .filter(|&n| n > 0)
        .ok_or_else(|| {
            Error::Usage(format!(
                "denoise: image size {width}×{height} is empty or too large"
            ))
        })?;
    for (name, image) in [("color", color), ("albedo", albedo), ("normal", normal)] {
        if image.len() != n {
            return Err(Error::Usage(format!(
                "denoise: the {name} image has {} pixels, expected {width}×{height} = {n}",
                image.len()
            )));
        }
    }
    if let Some(i) = color.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(Error::Usage(format!(
            "denoise: the color image has a non-finite value at pixel ({}, {}): {:?}",
            i % width,
            i / width,
            color[i]
        )));
    }
    Ok(())
}

#[cfg(feature = "denoise")]
fn oidn_rt(
    color: &[[f32; 3]],
    albedo: &[[f32; 3]],
    normal: &[[f32; 3]],
    width: usize,
    height: usize,
) -> std::result::Result<Vec<[f32; 3]>, oidn::Error> {
    let device = oidn::Device::cpu()?;
    // Buffers made here (fallible) rather than by `RayTracing::albedo_normal`, which panics
    // when an allocation fails.
    let albedo = device.create_buffer(bytemuck::cast_slice(albedo))?;
    let normal = device.create_buffer(bytemuck::cast_slice(normal))?;
    let mut filter = oidn::RayTracing::try_new(&device)?;
    filter
        .albedo_normal_buffer(albedo, normal)?
        .hdr(true)
        .image_dimensions(width, height);
    let mut out = vec![[0.0f32; 3]; color.len()];
    filter.filter(
        bytemuck::cast_slice(color),
        bytemuck::cast_slice_mut(&mut out),
    )?;
    Ok(out)
}
