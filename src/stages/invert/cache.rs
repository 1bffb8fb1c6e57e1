//! The training pixels' primary records, traced once (issue 12, "spend rays where they change
//! something").
//!
//! Stage 3 holds the geometry and the object poses fixed, so what a camera ray meets — its hits,
//! their weights w_j and the composited depth, position and normal (eq. surface-record) —
//! never changes; only the material sums Σ w_j m_j do, and those are recomputed from the kept
//! hits in a few multiply-adds ([`SurfaceRecord::set_materials`]). The material gradient of a
//! primary record then needs no tracing either: dL/dm_j = w_j · dL/dΣ
//! ([`crate::trace::scatter_material_grad`]). Every path sample of every iteration thus starts
//! at its shading point; only the rays that depend on the sampled lighting directions
//! (next-event visibility, the continuation) are traced.
//!
//! **The price: fixed sub-pixel positions.** The renderer draws a new filter-importance-sampled
//! position for every sample; here each pixel has `jitters` positions drawn once from the same
//! filter (Sobol samples 0..jitters of the pixel's stream under a fixed seed), and sample i uses
//! position i mod `jitters`. The pixel's expected estimate is then the mean over those positions
//! rather than the filter integral: identical inside a surface, a fixed (not noisy) error on
//! the pixels a silhouette crosses.
//!
//! **Memory**: per pixel and position one ray (32 B), one record (56 B), one offset (8 B) and
//! 12 B per composited hit; [`PrimaryCache::bytes`] reports it (stage 3's report states it).

use crate::io::dataset::Observation;
use crate::scene::{Rigid, Surfels};
use crate::shade::estimator::{PixelFilter, DEFAULT_FILTER_WIDTH};
use crate::shade::Sampler;
use crate::trace::{SurfaceRecord, TraceRay, TraceScene, WeightedHit};
use rayon::prelude::*;

/// One training state as the loop sees it: its captures and where every component stands.
pub struct TrainState<'a> {
    pub views: Vec<&'a Observation>,
    pub transforms: Vec<Rigid>,
    /// Secondary-ray offset ([`crate::shade::estimator::self_hit_epsilon`]).
    pub eps: f32,
}

/// Pixels per parallel work item when tracing the cache (fixed: the result does not depend on
/// the thread count; it would not anyway, each pixel's entries being independent).
const CHUNK: usize = 256;

/// [`PrimaryCache::figures`]: sub-pixel positions per pixel, entries (pixels × positions),
/// composited hits kept, heap bytes, and the seconds tracing them took.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CacheFigures {
    pub jitters: u32,
    pub entries: usize,
    pub hits: usize,
    pub bytes: usize,
    pub seconds: f64,
}

/// One work item's traced entries: rays, records, each entry's end in the hits, the hits.
type Traced = (
    Vec<TraceRay>,
    Vec<SurfaceRecord>,
    Vec<usize>,
    Vec<WeightedHit>,
);

/// Every training pixel's primary records, by image (training states' views in order), pixel
/// and sub-pixel position.
#[derive(Clone, Default)]
pub struct PrimaryCache {
    jitters: u32,
    /// Wall time of [`PrimaryCache::build`].
    seconds: f64,
    /// First entry of each image.
    image_start: Vec<usize>,
    rays: Vec<TraceRay>,
    records: Vec<SurfaceRecord>,
    /// Entry e's hits are `hits[hit_start[e]..hit_start[e + 1]]`.
    hit_start: Vec<usize>,
    hits: Vec<WeightedHit>,
}

impl std::fmt::Debug for PrimaryCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PrimaryCache")
            .field("jitters", &self.jitters)
            .field("entries", &self.records.len())
            .field("hits", &self.hits.len())
            .finish()
    }
}

impl PrimaryCache {
    /// Traces every pixel of every training view (`states`' views in order: image index
    /// `Σ_{k'<k} views(k') + v`) at `jitters` sub-pixel positions, each state's components
    /// placed by its transforms. `seed` fixes the positions.
    pub fn build(trace: &TraceScene, states: &[TrainState], jitters: u32, seed: u32) -> Self {
        assert!(jitters >= 1, "at least one sub-pixel position");
        let t0 = std::time::Instant::now();
        let filter = PixelFilter::new(DEFAULT_FILTER_WIDTH);
        let mut c = PrimaryCache {
            jitters,
            hit_start: vec![0],
            ..PrimaryCache::default()
        };
        for st in states {
            let placed = trace.place(&st.transforms);
            for obs in &st.views {
                c.image_start.push(c.records.len());
                let cam = &obs.camera;
                let npix = (cam.w * cam.h) as usize;
                let chunks: Vec<Traced> = (0..npix)
                    .collect::<Vec<_>>()
                    .par_chunks(CHUNK)
                    .map(|ps| {
                        let mut out = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
                        for &p in ps {
                            let p = p as u32;
                            let sampler = Sampler::new(p, seed);
                            for j in 0..jitters {
                                let (o, d) =
                                    filter.camera_ray(cam, (p % cam.w, p / cam.w), &sampler, j);
                                let ray = TraceRay {
                                    origin: o,
                                    dir: d,
                                    t_min: 0.0,
                                    t_max: f32::INFINITY,
                                };
                                let rec =
                                    placed.composite_hits(o, d, 0.0, f32::INFINITY, &mut out.3);
                                out.0.push(ray);
                                out.1.push(rec);
                                out.2.push(out.3.len());
                            }
                        }
                        out
                    })
                    .collect();
                for (rays, records, ends, hits) in chunks {
                    let base = c.hits.len();
                    c.rays.extend(rays);
                    c.records.extend(records);
                    c.hit_start.extend(ends.iter().map(|e| base + e));
                    c.hits.extend(hits);
                }
            }
        }
        c.seconds = t0.elapsed().as_secs_f64();
        c
    }

    /// What the cache holds and cost, for reports.
    pub fn figures(&self) -> CacheFigures {
        CacheFigures {
            jitters: self.jitters,
            entries: self.records.len(),
            hits: self.hits.len(),
            bytes: self.bytes(),
            seconds: self.seconds,
        }
    }

    pub fn jitters(&self) -> u32 {
        self.jitters
    }

    /// The entry sample `sample` of pixel `pixel` of image `image` uses.
    #[inline]
    pub fn entry(&self, image: usize, pixel: u32, sample: u32) -> usize {
        self.image_start[image]
            + pixel as usize * self.jitters as usize
            + (sample % self.jitters) as usize
    }

    /// Entry `e`'s camera ray and record, its material sums made from `components`' current
    /// materials.
    #[inline]
    pub fn record(&self, e: usize, components: &[&Surfels]) -> (TraceRay, SurfaceRecord) {
        let mut rec = self.records[e];
        rec.set_materials(self.hits(e), components);
        (self.rays[e], rec)
    }

    /// Entry `e`'s camera ray and record without its material sums (opacity, position and
    /// normal only: what depends on the fixed geometry alone).
    #[inline]
    pub fn geometry(&self, e: usize) -> (TraceRay, SurfaceRecord) {
        (self.rays[e], self.records[e])
    }

    /// Entry `e`'s composited hits, front to back.
    #[inline]
    pub fn hits(&self, e: usize) -> &[WeightedHit] {
        &self.hits[self.hit_start[e]..self.hit_start[e + 1]]
    }

    /// Entries (pixels × positions) and hits kept.
    pub fn len(&self) -> (usize, usize) {
        (self.records.len(), self.hits.len())
    }

    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// Heap bytes held.
    pub fn bytes(&self) -> usize {
        use std::mem::size_of;
        self.rays.capacity() * size_of::<TraceRay>()
            + self.records.capacity() * size_of::<SurfaceRecord>()
            + self.hit_start.capacity() * size_of::<usize>()
            + self.hits.capacity() * size_of::<WeightedHit>()
            + self.image_start.capacity() * size_of::<usize>()
    }
}
