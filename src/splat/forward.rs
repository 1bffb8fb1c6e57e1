//! The forward tile loop: front-to-back compositing (eq. surface-record) of each tile's
//! depth-sorted list, surfel by surfel over the tile's pixels, so a surfel is read once per tile
//! and the per-pixel state (256 pixels) stays in L1.

use super::project::{prefetch, row_hits, Bins, Splat, View};
use super::{SplatImage, TILE, TILE_PIXELS, T_MIN};
use rayon::prelude::*;

/// How many list entries ahead the tile loops prefetch: a splat's pixels take a few hundred
/// cycles, about one memory latency.
pub(crate) const PREFETCH_AHEAD: usize = 4;

/// What the backward pass needs of each pixel, tile-major (256 slots per tile, pixels outside
/// the image unused).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct PixelState {
    /// Final transmittance.
    pub t: f32,
    /// One past the tile-list position of the last composited hit (0: none).
    pub last: u32,
    /// One plus the tile-list position of the median-depth hit (0: none).
    pub median: u32,
}

/// Accumulated outputs of one pixel, before the depth is divided by the opacity.
#[derive(Clone, Copy, Debug, Default)]
struct PixelOut {
    color: [f32; 3],
    alpha: f32,
    depth: f32,
    median: f32,
    normal: [f32; 3],
}

/// The pixel range of a tile, clipped to the image: (x0, y0, x1, y1).
#[inline]
pub(crate) fn tile_pixels(view: &View, tile: usize) -> (u32, u32, u32, u32) {
    let tx = tile as u32 % view.tiles_x;
    let ty = tile as u32 / view.tiles_x;
    let (x0, y0) = (tx * TILE, ty * TILE);
    (
        x0,
        y0,
        (x0 + TILE).min(view.width),
        (y0 + TILE).min(view.height),
    )
}

/// The part of a surfel's rectangle inside the tile's pixel range.
#[inline]
pub(crate) fn clip(s: &Splat, (x0, y0, x1, y1): (u32, u32, u32, u32)) -> (u32, u32, u32, u32) {
    (
        s.rect[0].max(x0),
        s.rect[1].max(y0),
        s.rect[2].min(x1),
        s.rect[3].min(y1),
    )
}

pub(crate) fn rasterize(
    view: &View,
    splats: &[Splat],
    bins: &Bins,
) -> (SplatImage, Vec<PixelState>) {
    let tiles = view.tiles();
    let mut states = vec![PixelState::default(); tiles * TILE_PIXELS];
    let mut outs = vec![PixelOut::default(); tiles * TILE_PIXELS];
    states
        .par_chunks_mut(TILE_PIXELS)
        .zip(outs.par_chunks_mut(TILE_PIXELS))
        .enumerate()
        .for_each(|(tile, (st, out))| {
            forward_tile(view, splats, bins.tile_list(tile), tile, st, out);
        });

    let mut image = SplatImage::zeros(view.width, view.height);
    for tile in 0..tiles {
        let (x0, y0, x1, y1) = tile_pixels(view, tile);
        for y in y0..y1 {
            for x in x0..x1 {
                let o = &outs[tile * TILE_PIXELS + ((y - y0) * TILE + (x - x0)) as usize];
                let i = (y * view.width + x) as usize;
                image.color[i] = o.color;
                image.alpha[i] = o.alpha;
                image.depth[i] = if o.alpha > 0.0 {
                    o.depth / o.alpha
                } else {
                    0.0
                };
                image.median_depth[i] = o.median;
                image.normal[i] = o.normal;
            }
        }
    }
    (image, states)
}

/// Bit `x − x0` of row `y − y0` for the pixels of a tile row in `[sx0, sx1)` (within the tile).
#[inline]
pub(crate) fn row_bits(x0: u32, sx0: u32, sx1: u32) -> u32 {
    if sx1 <= sx0 {
        return 0;
    }
    let (a, b) = (sx0 - x0, sx1 - x0);
    // b ≤ TILE = 16, so the shifts cannot overflow a u32.
    ((1u32 << b) - 1) & !((1u32 << a) - 1)
}

fn forward_tile(
    view: &View,
    splats: &[Splat],
    list: &[u32],
    tile: usize,
    st: &mut [PixelState],
    out: &mut [PixelOut],
) {
    let bounds = tile_pixels(view, tile);
    let (x0, y0, x1, y1) = bounds;
    for s in st.iter_mut() {
        s.t = 1.0;
    }
    // Per tile row, the pixels still compositing (bit x − x0): a pixel leaves once its
    // transmittance falls below T_MIN, and the loops visit only the bits that remain.
    let mut open = [0u32; TILE as usize];
    for row in open.iter_mut().take((y1 - y0) as usize) {
        *row = row_bits(x0, x0, x1);
    }
    let mut live = (x1 - x0) * (y1 - y0);
    for (k, &i) in list.iter().enumerate() {
        if live == 0 {
            break;
        }
        if let Some(&ahead) = list.get(k + PREFETCH_AHEAD) {
            prefetch(splats, ahead as usize);
        }
        let s = &splats[i as usize];
        let (sx0, sy0, sx1, sy1) = clip(s, bounds);
        let cols = row_bits(x0, sx0, sx1);
        for y in sy0..sy1 {
            let v = y as f32 + 0.5;
            let r = (y - y0) as usize;
            for (bit, _, h) in row_hits(s, x0, v, open[r] & cols) {
                let p = r * TILE as usize + bit as usize;
                let ps = &mut st[p];
                let o = &mut out[p];
                let w = h.alpha * ps.t;
                for c in 0..3 {
                    o.color[c] += w * s.color[c];
                    o.normal[c] += w * s.normal[c];
                }
                o.alpha += w;
                o.depth += w * h.z;
                // 2DGS's median: the last hit entered while more than half the light remains.
                if ps.t > 0.5 {
                    o.median = h.z;
                    ps.median = k as u32 + 1;
                }
                ps.t *= 1.0 - h.alpha;
                ps.last = k as u32 + 1;
                if ps.t < T_MIN {
                    open[r] &= !(1 << bit);
                    live -= 1;
                }
            }
        }
    }
}
