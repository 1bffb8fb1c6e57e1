//! The estimator-to-image loop: every pixel of a camera through the one-bounce estimator
//! ([`crate::shade::estimator`]), rayon over square tiles, gathered into named float channels.
//!
//! Channels: `R, G, B` (radiance, scene-linear Rec.709, the environment included behind partial
//! coverage), `A` (mean coverage), `Z` (planar depth, DESIGN §2; 0 = no hit), `N.X, N.Y, N.Z`
//! (unit world normal facing the camera), `albedo.R/G/B` (base colour); the AOVs come from the
//! record at the pixel centre. Pixel (x, y) draws from the Sobol stream
//! `Sampler::new(y·w + x, seed)`.

use crate::io::exr::Channels;
use crate::scene::Camera;
use crate::shade::estimator::{Estimator, Pixel, PixelFilter};
use rayon::prelude::*;

/// Image tiles are this many pixels square; a tile is one rayon task.
pub const TILE: u32 = 16;

/// The channels [`render_image`] returns, in order.
pub const CHANNELS: [&str; 11] = [
    "R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z", "albedo.R", "albedo.G", "albedo.B",
];

/// Renders one camera with `spp` samples per pixel: the image's channels ([`CHANNELS`]) and the
/// number of rays traced. `progress` is told the number of pixels of each finished tile (from
/// rayon's threads).
pub fn render_image(
    estimator: &Estimator,
    filter: &PixelFilter,
    camera: &Camera,
    spp: u32,
    seed: u32,
    progress: &(dyn Fn(u64) + Sync),
) -> (Channels, u64) {
    let (w, h) = (camera.w, camera.h);
    let tiles: Vec<(u32, u32)> = (0..h.div_ceil(TILE))
        .flat_map(|ty| (0..w.div_ceil(TILE)).map(move |tx| (tx * TILE, ty * TILE)))
        .collect();
    let rendered: Vec<((u32, u32), [Pixel; (TILE * TILE) as usize])> = tiles
        .par_iter()
        .map(|&(x0, y0)| {
            let mut buf = [Pixel::default(); (TILE * TILE) as usize];
            let (x1, y1) = ((x0 + TILE).min(w), (y0 + TILE).min(h));
            for y in y0..y1 {
                for x in x0..x1 {
                    buf[((y - y0) * TILE + (x - x0)) as usize] =
                        estimator.pixel(camera, filter, (x, y), spp, seed);
                }
            }
            progress(((x1 - x0) * (y1 - y0)) as u64);
            ((x0, y0), buf)
        })
        .collect();
    let n = (w * h) as usize;
    let mut planes = vec![vec![0.0f32; n]; CHANNELS.len()];
    let mut rays = 0u64;
    for ((x0, y0), buf) in &rendered {
        for y in *y0..(y0 + TILE).min(h) {
            for x in *x0..(x0 + TILE).min(w) {
                let p = &buf[((y - y0) * TILE + (x - x0)) as usize];
                let i = (y * w + x) as usize;
                let values = [
                    p.rgb[0],
                    p.rgb[1],
                    p.rgb[2],
                    p.alpha,
                    p.depth,
                    p.normal[0],
                    p.normal[1],
                    p.normal[2],
                    p.albedo[0],
                    p.albedo[1],
                    p.albedo[2],
                ];
                for (plane, v) in planes.iter_mut().zip(values) {
                    plane[i] = v;
                }
                rays += p.rays as u64;
            }
        }
    }
    let channels = CHANNELS
        .iter()
        .zip(planes)
        .map(|(name, v)| (name.to_string(), v))
        .collect();
    (
        Channels {
            width: w as usize,
            height: h as usize,
            channels,
        },
        rays,
    )
}
