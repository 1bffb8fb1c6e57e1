//! The estimator-to-image loop: every pixel of a camera through the one-bounce estimator
//! ([`crate::shade::estimator`]), rayon over square tiles, gathered into a [`RenderedImage`].
//!
//! What a pixel holds: radiance (scene-linear Rec.709, the environment included behind partial
//! coverage) and the AOVs of the record at the pixel centre: mean coverage, planar depth
//! (docs/design.md §2; 0 = no hit), unit world normal facing the camera and base
//! colour. Pixel (x, y) draws from the Sobol stream `Sampler::new(y·w + x, seed)`. How an image
//! is stored (EXR channel names) is `io::exr`'s business, not the renderer's.

use crate::scene::Camera;
use crate::scene::Material;
use crate::shade::estimator::{camera_forward, Estimator, Pixel, PixelFilter};
use crate::shade::sobol::Sampler;
use crate::trace::{Placed, SurfaceRecord, TraceRay};
use glam::Vec3;
use rayon::prelude::*;

/// Image tiles are this many pixels square; a tile is one rayon task.
pub const TILE: u32 = 16;

/// A rendered view: radiance and the pixel-centre AOVs, row-major, `width * height` each.
/// [`render_image`] leaves `aovs.metallic` and `aovs.roughness` empty (they are no guides and
/// no output of `lightfuse render`); a splatted (baked) image leaves `aovs.albedo` empty too.
pub struct RenderedImage {
    pub width: usize,
    pub height: usize,
    pub radiance: Vec<[f32; 3]>,
    pub aovs: Aovs,
}

/// Renders one camera with `spp` samples per pixel: the image and the number of rays traced. `progress` is told the number of pixels of each finished tile (from
/// rayon's threads).
pub fn render_image(
    estimator: &Estimator,
    filter: &PixelFilter,
    camera: &Camera,
    spp: u32,
    seed: u32,
    progress: &(dyn Fn(u64) + Sync),
) -> (RenderedImage, u64) {
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
    let mut image = RenderedImage {
        width: w as usize,
        height: h as usize,
        radiance: vec![[0.0; 3]; n],
        aovs: Aovs {
            alpha: vec![0.0; n],
            depth: vec![0.0; n],
            normal: vec![[0.0; 3]; n],
            albedo: vec![[0.0; 3]; n],
            metallic: Vec::new(),
            roughness: Vec::new(),
        },
    };
    let mut rays = 0u64;
    for ((x0, y0), buf) in &rendered {
        for y in *y0..(y0 + TILE).min(h) {
            for x in *x0..(x0 + TILE).min(w) {
                let p = &buf[((y - y0) * TILE + (x - x0)) as usize];
                let i = (y * w + x) as usize;
                image.radiance[i] = p.rgb;
                image.aovs.alpha[i] = p.alpha;
                image.aovs.depth[i] = p.depth;
                image.aovs.normal[i] = p.normal;
                image.aovs.albedo[i] = p.albedo;
                rays += p.rays as u64;
            }
        }
    }
    (image, rays)
}

/// The environment seen along each pixel centre's camera ray of `camera` (row-major): what a
/// pixel shows where nothing covers it.
pub fn environment_image(env: &crate::shade::EnvMap, camera: &Camera) -> Vec<[f32; 3]> {
    (0..camera.h)
        .flat_map(|y| (0..camera.w).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (_, d) = camera.ray(x as f32 + 0.5, y as f32 + 0.5);
            env.eval(Vec3::from_array(d))
        })
        .collect()
}

/// Every path sample's camera ray and primary record of one camera, traced once. Geometry and
/// placement alone decide them (the camera ray's filter jitter comes from the pixel's Sobol
/// stream, the record from compositing), so renders of the same view under several
/// environments, or with other materials, can share them: [`Primaries::shade`] then traces only
/// the rays after the primary hit. Pixel (x, y) draws from `Sampler::new(y·w + x, seed)`, as
/// [`render_image`] does, so the two agree sample for sample.
///
/// Memory: 88 bytes per sample (a 32-byte ray and a 56-byte record), e.g. 35 MB for 128×96 at
/// 32 spp, 216 MB for 320×240.
pub struct Primaries {
    pub camera: Camera,
    pub spp: u32,
    pub seed: u32,
    /// Pixel-major: sample i of pixel p at `p · spp + i`.
    samples: Vec<(TraceRay, SurfaceRecord)>,
    /// The record at each pixel's centre (the AOVs).
    centre: Vec<SurfaceRecord>,
    /// Camera rays traced.
    pub rays: u64,
}

/// Per-pixel AOVs of [`Primaries`]: from the record at the pixel centre (as [`render_image`]'s),
/// zero where nothing is hit.
pub struct Aovs {
    /// Mean coverage over the samples.
    pub alpha: Vec<f32>,
    /// Planar depth (docs/design.md §2).
    pub depth: Vec<f32>,
    /// Unit world normal facing the camera.
    pub normal: Vec<[f32; 3]>,
    /// Base colour.
    pub albedo: Vec<[f32; 3]>,
    pub metallic: Vec<f32>,
    pub roughness: Vec<f32>,
}

impl Primaries {
    /// Traces every sample's camera ray of `camera` through `scene` (rayon over rows).
    pub fn trace(
        scene: &Placed,
        filter: &PixelFilter,
        camera: &Camera,
        spp: u32,
        seed: u32,
    ) -> Primaries {
        let (w, h) = (camera.w, camera.h);
        type Row = (Vec<(TraceRay, SurfaceRecord)>, Vec<SurfaceRecord>);
        let rows: Vec<Row> = (0..h)
            .into_par_iter()
            .map(|y| {
                let mut samples = Vec::with_capacity((w * spp) as usize);
                let mut centre = Vec::with_capacity(w as usize);
                for x in 0..w {
                    let sampler = Sampler::new(y * w + x, seed);
                    for i in 0..spp {
                        let (o, d) = filter.camera_ray(camera, (x, y), &sampler, i);
                        let ray = TraceRay {
                            origin: o,
                            dir: d,
                            t_min: 0.0,
                            t_max: f32::INFINITY,
                        };
                        samples.push((ray, scene.composite(o, d, 0.0, f32::INFINITY)));
                    }
                    let (o, d) = camera.ray(x as f32 + 0.5, y as f32 + 0.5);
                    centre.push(scene.composite(o, d, 0.0, f32::INFINITY));
                }
                (samples, centre)
            })
            .collect();
        let mut samples = Vec::with_capacity((w * h * spp) as usize);
        let mut centre = Vec::with_capacity((w * h) as usize);
        for (s, c) in rows {
            samples.extend(s);
            centre.extend(c);
        }
        Primaries {
            camera: *camera,
            spp,
            seed,
            samples,
            centre,
            rays: w as u64 * h as u64 * (spp as u64 + 1),
        }
    }

    /// The pixels' AOVs.
    pub fn aovs(&self) -> Aovs {
        let (w, spp) = (self.camera.w as usize, self.spp as usize);
        let fwd = camera_forward(&self.camera);
        let n = self.centre.len();
        let mut a = Aovs {
            alpha: vec![0.0; n],
            depth: vec![0.0; n],
            normal: vec![[0.0; 3]; n],
            albedo: vec![[0.0; 3]; n],
            metallic: vec![0.0; n],
            roughness: vec![0.0; n],
        };
        for (p, rec) in self.centre.iter().enumerate() {
            let s = &self.samples[p * spp..(p + 1) * spp];
            a.alpha[p] = s.iter().map(|(_, r)| r.alpha).sum::<f32>() / spp.max(1) as f32;
            if rec.hits > 0 && rec.alpha > 0.0 {
                let (x, y) = ((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
                let (_, d) = self.camera.ray(x, y);
                a.depth[p] = rec.mean_depth() * Vec3::from_array(d).dot(fwd);
                a.normal[p] = rec.unit_normal();
                a.albedo[p] = rec.mean_base_color();
                a.metallic[p] = rec.mean_metallic();
                a.roughness[p] = rec.mean_roughness();
            }
        }
        a
    }

    /// The image `estimator` renders from these primaries (its scene must be the one traced),
    /// once per entry of `base_color_scales`: each record's mean base colour multiplied by the
    /// scale and clamped to [0, 1] ([1, 1, 1]: as rendered), every other decision the same
    /// (the path's sampling was drawn with the unscaled materials and is held fixed, as in path
    /// replay, so each image is an unbiased estimate with its own materials). Returns the images
    /// (row-major mean radiance per pixel) and the rays traced after the primary hit.
    pub fn shade(
        &self,
        estimator: &Estimator,
        base_color_scales: &[[f32; 3]],
    ) -> (Vec<Vec<[f32; 3]>>, u64) {
        let spp = self.spp as usize;
        let k = base_color_scales.len();
        let scaled = |m: &Material, s: &[f32; 3]| Material {
            base_color: [0, 1, 2].map(|c| (m.base_color[c] * s[c]).clamp(0.0, 1.0)),
            ..*m
        };
        let per_pixel: Vec<(Vec<[f32; 3]>, u64)> = (0..self.centre.len())
            .into_par_iter()
            .with_min_len(64)
            .map(|p| {
                let sampler = Sampler::new(p as u32, self.seed);
                let mut acc = vec![[0.0f32; 3]; k];
                let mut rays = 0u64;
                for (i, (ray, rec)) in self.samples[p * spp..(p + 1) * spp].iter().enumerate() {
                    let path = estimator.replay_from(*ray, *rec, &sampler, i as u32);
                    rays += path.rays as u64;
                    for (a, s) in acc.iter_mut().zip(base_color_scales) {
                        let v = if *s == [1.0; 3] {
                            path.radiance(estimator.env)
                        } else {
                            let m = [scaled(&path.materials[0], s), scaled(&path.materials[1], s)];
                            path.radiance_with(&m, estimator.env)
                        };
                        for c in 0..3 {
                            a[c] += v[c];
                        }
                    }
                }
                let inv = 1.0 / spp.max(1) as f32;
                (acc.into_iter().map(|a| a.map(|v| v * inv)).collect(), rays)
            })
            .collect();
        let mut images = vec![Vec::with_capacity(self.centre.len()); k];
        let mut rays = 0;
        for (px, r) in per_pixel {
            rays += r;
            for (img, v) in images.iter_mut().zip(px) {
                img.push(v);
            }
        }
        (images, rays)
    }
}
