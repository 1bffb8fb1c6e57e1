//! From surfels and a camera to what the tile loops read: the camera as affine pixel rays, each
//! surfel's hit test as a handful of affine coefficients (2DGS's homography, written as a ray–
//! plane intersection), its colour, its pixel rectangle, and the depth-sorted tile lists.

use super::{sh, Placement, FILTER_INV_VARIANCE, MIN_ALPHA, NEAR, TILE};
use crate::kernel::{r2_max, response};
use crate::scene::{Camera, Surfels};
use glam::{Mat3, Quat, Vec3, Vec4};
use rayon::prelude::*;

/// The camera as the rasteriser uses it. The ray through pixel coordinates (u, v) is
/// `d(u, v) = d0 + u du + v dv` with `d · fwd = 1`, so the ray parameter of a hit is its planar
/// depth (docs/design.md §2), and `d` is affine in (u, v): every per-pixel dot product is too.
#[derive(Clone, Copy, Debug)]
pub(crate) struct View {
    pub o: Vec3,
    pub right: Vec3,
    pub up: Vec3,
    /// The viewing axis, −Z of the camera (OpenGL convention).
    pub fwd: Vec3,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
    pub tiles_x: u32,
    pub tiles_y: u32,
    pub d0: Vec3,
    pub du: Vec3,
    pub dv: Vec3,
}

impl View {
    pub fn new(camera: &Camera) -> View {
        let col = |c: usize| Vec3::from_array(camera.axis(c));
        let (right, up, fwd) = (col(0), col(1), -col(2));
        let du = right / camera.fl_x;
        let dv = -up / camera.fl_y;
        View {
            o: col(3),
            right,
            up,
            fwd,
            fx: camera.fl_x,
            fy: camera.fl_y,
            cx: camera.cx,
            cy: camera.cy,
            width: camera.w,
            height: camera.h,
            tiles_x: camera.w.div_ceil(TILE),
            tiles_y: camera.h.div_ceil(TILE),
            d0: fwd - camera.cx * du - camera.cy * dv,
            du,
            dv,
        }
    }

    pub fn tiles(&self) -> usize {
        self.tiles_x as usize * self.tiles_y as usize
    }

    /// Pixel coordinates of the world offset `a = x − o` (which must lie in front).
    #[inline]
    pub fn project(&self, a: Vec3) -> [f32; 2] {
        let z = a.dot(self.fwd);
        [
            self.cx + self.fx * a.dot(self.right) / z,
            self.cy - self.fy * a.dot(self.up) / z,
        ]
    }
}

/// One surfel placed in the world: what the forward pass and the backward pass both derive the
/// same way from the inputs.
pub(crate) struct WorldSurfel {
    pub p: Vec3,
    /// Columns t_u, t_v, n.
    pub axes: Mat3,
    pub scale: [f32; 2],
    pub opacity: f32,
}

/// The placement's rotation matrix and translation.
pub(crate) fn placement_frame(p: &Placement) -> (Mat3, Vec3) {
    (
        Mat3::from_quat(p.transform.quat().normalize()),
        Vec3::from_array(p.transform.translation),
    )
}

/// Surfel `i` placed by (R_T, t_T) (eq. state-assembly: centre and orientation only).
#[inline]
pub(crate) fn world_surfel(s: &Surfels, i: usize, rot: Mat3, trans: Vec3) -> WorldSurfel {
    let q = Quat::from_array(s.rotation[i]).normalize();
    WorldSurfel {
        p: rot * Vec3::from_array(s.position[i]) + trans,
        axes: rot * Mat3::from_quat(q),
        scale: s.scale[i],
        opacity: s.opacity[i],
    }
}

/// The normal turned to face the camera (2DGS flips it when n · (μ − o) > 0).
#[inline]
pub(crate) fn facing_sign(n: Vec3, a: Vec3) -> f32 {
    if n.dot(a) > 0.0 {
        -1.0
    } else {
        1.0
    }
}

/// A surfel as the tile loops read it: two cache lines, fetched ahead with [`prefetch`].
///
/// With `w_u = t_u / s_u`, `w_v = t_v / s_v` and the pixel ray `d(u, v)`, the hit of
/// eq. gaussian-response is `t = (a·n) / (d·n)`, `ξ_u = t (d·w_u) − a·w_u`, `ξ_v` alike
/// (`a = μ − o`); the three dot products with `d` are affine in (u, v) with coefficients
/// `hu`, `hv`, `hn` = (d0·w, du·w, dv·w).
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(64))]
pub(crate) struct Splat {
    pub hu: [f32; 3],
    pub hv: [f32; 3],
    pub hn: [f32; 3],
    /// a·w_u, a·w_v, a·n.
    pub au: f32,
    pub av: f32,
    pub an: f32,
    /// Projected centre, pixels.
    pub c: [f32; 2],
    /// Centre depth, the sort key.
    pub zc: f32,
    pub opacity: f32,
    /// Largest ρ that can pass both the support and the opacity threshold:
    /// [`crate::kernel::r2_max`]; the exact tests in [`hit`] decide.
    pub rho_max: f32,
    /// Colour after the clamp at 0.
    pub color: [f32; 3],
    /// Unit normal facing the camera.
    pub normal: [f32; 3],
    /// Pixel rectangle [x0, x1) × [y0, y1) that can be hit, never empty.
    pub rect: [u32; 4],
}

/// Asks for a splat's two cache lines ahead of use. A tile visits its splats in depth order,
/// scattered over the input-ordered array, which the hardware prefetcher cannot follow; the hit
/// loops were measured to spend a fifth of their time waiting for the first load of each splat.
#[inline(always)]
pub(crate) fn prefetch(splats: &[Splat], k: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(s) = splats.get(k) {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let p = s as *const Splat as *const i8;
        // SAFETY: prefetching is a hint that never faults, and `p` points into a live slice.
        unsafe {
            _mm_prefetch(p, _MM_HINT_T0);
            _mm_prefetch(p.add(64), _MM_HINT_T0);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (splats, k);
}

/// What one pixel sees of one surfel, with the intermediates the backward pass needs.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Hit {
    pub alpha: f32,
    /// Ĝ = exp(−½ ρ).
    pub g: f32,
    /// opacity · Ĝ exceeded MAX_OPACITY: α does not depend on the parameters.
    pub clamped: bool,
    /// Planar depth of the hit.
    pub z: f32,
    /// ρ came from the plane (ρ_3d ≤ ρ_2d), not from the low-pass filter.
    pub plane: bool,
    pub t: f32,
    /// d·n, d·w_u, d·w_v.
    pub den: f32,
    pub du: f32,
    pub dv: f32,
    pub xu: f32,
    pub xv: f32,
    /// c − p, pixels.
    pub dx: f32,
    pub dy: f32,
}

/// The hit of the ray through pixel coordinates (u, v) (eq. gaussian-response with 2DGS's
/// low-pass filter), or `None` if it is dropped. A ray in the surfel's plane gives t = ±∞ or
/// NaN, ρ_3d = ∞ or NaN, and the comparison below then takes the filter's ρ_2d.
///
/// The specification of [`hit4`], which the tile loops call: the tests hold the two equal bit
/// for bit, lane by lane.
#[cfg(test)]
pub(crate) fn hit(s: &Splat, u: f32, v: f32) -> Option<Hit> {
    let den = s.hn[0] + s.hn[1] * u + s.hn[2] * v;
    let du = s.hu[0] + s.hu[1] * u + s.hu[2] * v;
    let dv = s.hv[0] + s.hv[1] * u + s.hv[2] * v;
    let t = s.an / den;
    let xu = t * du - s.au;
    let xv = t * dv - s.av;
    let rho_3d = xu * xu + xv * xv;
    let dx = s.c[0] - u;
    let dy = s.c[1] - v;
    let rho_2d = FILTER_INV_VARIANCE * (dx * dx + dy * dy);
    let plane = rho_3d <= rho_2d;
    let (rho, z) = if plane { (rho_3d, t) } else { (rho_2d, s.zc) };
    if !(rho <= s.rho_max && z >= NEAR) {
        return None;
    }
    let r = response(s.opacity, rho)?;
    Some(Hit {
        alpha: r.alpha,
        g: r.g,
        clamped: r.capped,
        z,
        plane,
        t,
        den,
        du,
        dv,
        xu,
        xv,
        dx,
        dy,
    })
}

/// Every hit of `s` among the pixels of one tile row: columns `x0 + bit` for the set bits of
/// `m` (those still to visit), at row coordinate `v`; `(bit, u, hit)`, lowest bit first. Tested
/// four pixels at a time ([`hit4`]): a (surfel, row) pair has 3.2 pixels still to visit on
/// average (counted on `cargo bench --bench splat`'s scene), so four lanes, not a row's sixteen.
/// The forward and backward tile loops both take their hits from here.
#[inline(always)]
pub(crate) fn row_hits(s: &Splat, x0: u32, v: f32, m: u32) -> RowHits<'_> {
    RowHits {
        s,
        x0,
        v,
        m,
        bits: [0; 4],
        u: [0.0; 4],
        kept: 0,
        hits: None,
    }
}

/// The iterator [`row_hits`] returns.
pub(crate) struct RowHits<'a> {
    s: &'a Splat,
    x0: u32,
    v: f32,
    /// Columns not yet tested.
    m: u32,
    /// The current group's columns and coordinates, and its lanes not yet returned.
    bits: [u32; 4],
    u: [f32; 4],
    kept: u32,
    hits: Option<Hits4>,
}

impl Iterator for RowHits<'_> {
    type Item = (u32, f32, Hit);

    #[inline(always)]
    fn next(&mut self) -> Option<Self::Item> {
        loop {
            while self.kept != 0 {
                let lane = self.kept.trailing_zeros() as usize;
                self.kept &= self.kept - 1;
                if let Some(h) = self.hits.as_ref().and_then(|hits| hits.get(lane)) {
                    return Some((self.bits[lane], self.u[lane], h));
                }
            }
            if self.m == 0 {
                return None;
            }
            // The next four columns; unused lanes repeat the first (and are not `live`).
            let mut live = 0u32;
            self.bits = [self.m.trailing_zeros(); 4];
            for (lane, b) in self.bits.iter_mut().enumerate() {
                if self.m == 0 {
                    break;
                }
                *b = self.m.trailing_zeros();
                self.m &= self.m - 1;
                live |= 1 << lane;
            }
            self.u = self.bits.map(|b| (self.x0 + b) as f32 + 0.5);
            let hits = hit4(self.s, Vec4::from_array(self.u), self.v, live);
            self.kept = hits.kept;
            self.hits = Some(hits);
        }
    }
}

/// [`hit`] for four pixels of one row, `u` their column coordinates and `v` the row's: the
/// same operations in the same order on each lane (glam's `Vec4` is four single-precision
/// lanes with IEEE division, and nothing is fused), so each lane's result is `hit`'s bit for
/// bit; only the response's `exp`, which few lanes reach, stays scalar ([`Hits4::get`]).
/// Forward and backward both call this through [`row_hits`], so they agree bit for bit on
/// which hits exist. Only lanes of `live` can be kept.
#[inline(always)]
pub(crate) fn hit4(s: &Splat, u: Vec4, v: f32, live: u32) -> Hits4 {
    let splat = Vec4::splat;
    let vv = splat(v);
    let den = splat(s.hn[0]) + splat(s.hn[1]) * u + splat(s.hn[2]) * vv;
    let du = splat(s.hu[0]) + splat(s.hu[1]) * u + splat(s.hu[2]) * vv;
    let dv = splat(s.hv[0]) + splat(s.hv[1]) * u + splat(s.hv[2]) * vv;
    let t = splat(s.an) / den;
    let xu = t * du - splat(s.au);
    let xv = t * dv - splat(s.av);
    let rho_3d = xu * xu + xv * xv;
    let dx = splat(s.c[0]) - u;
    let dy = s.c[1] - v;
    let rho_2d = splat(FILTER_INV_VARIANCE) * (dx * dx + splat(dy * dy));
    let plane = rho_3d.cmple(rho_2d);
    let rho = Vec4::select(plane, rho_3d, rho_2d);
    let z = Vec4::select(plane, t, splat(s.zc));
    let kept = live & (rho.cmple(splat(s.rho_max)) & z.cmpge(splat(NEAR))).bitmask();
    Hits4 {
        kept,
        plane: plane.bitmask(),
        opacity: s.opacity,
        rho,
        z,
        t,
        den,
        du,
        dv,
        xu,
        xv,
        dx,
        dy,
    }
}

/// [`hit4`]'s lanes before the response: [`Hits4::get`] finishes one lane.
pub(crate) struct Hits4 {
    /// Lanes that passed the support and near tests.
    pub kept: u32,
    plane: u32,
    opacity: f32,
    rho: Vec4,
    z: Vec4,
    t: Vec4,
    den: Vec4,
    du: Vec4,
    dv: Vec4,
    xu: Vec4,
    xv: Vec4,
    dx: Vec4,
    dy: f32,
}

impl Hits4 {
    /// Lane `lane`'s hit, `None` unless it is kept and its α reaches MIN_ALPHA.
    #[inline(always)]
    pub fn get(&self, lane: usize) -> Option<Hit> {
        if self.kept & (1 << lane) == 0 {
            return None;
        }
        let r = response(self.opacity, self.rho[lane])?;
        Some(Hit {
            alpha: r.alpha,
            g: r.g,
            clamped: r.capped,
            z: self.z[lane],
            plane: self.plane & (1 << lane) != 0,
            t: self.t[lane],
            den: self.den[lane],
            du: self.du[lane],
            dv: self.dv[lane],
            xu: self.xu[lane],
            xv: self.xv[lane],
            dx: self.dx[lane],
            dy: self.dy,
        })
    }
}

/// Margin of a pixel rectangle, pixels: the rectangle is computed in f32 too.
const RECT_MARGIN: f32 = 0.01;

/// Every surfel as a splat, by global index (a culled one has a NaN `zc` and is in no list),
/// and the visible ones' order front to back by centre depth (ties by global index), as 2DGS
/// sorts each tile. The splats are not moved into that order: the tile loops prefetch them
/// ahead of use, and moving 128-byte records costs more than it saves.
pub(crate) struct Prepared {
    pub splats: Vec<Splat>,
    /// Global index of the k-th visible splat, front to back.
    pub order: Vec<u32>,
    /// Sorted index k of each global surfel, `CULLED` if it is not drawn.
    pub sorted_of: Vec<u32>,
}

pub(crate) const CULLED: u32 = u32::MAX;

/// Projects every surfel of every placement (global index = component offset + index).
pub(crate) fn prepare(view: &View, components: &[Placement], offsets: &[usize]) -> Prepared {
    let total = offsets[components.len()];
    if view.width == 0 || view.height == 0 {
        return Prepared {
            splats: Vec::new(),
            order: Vec::new(),
            sorted_of: vec![CULLED; total],
        };
    }
    // In input order (the inputs are read sequentially): cull, and build what survives
    // (a culled surfel is marked by a NaN depth).
    let frames: Vec<_> = components.iter().map(placement_frame).collect();
    let splats: Vec<Splat> = (0..total)
        .into_par_iter()
        .with_min_len(512)
        .map(|g| {
            let c = offsets.partition_point(|&o| o <= g) - 1;
            let (pl, i) = (&components[c], g - offsets[c]);
            let (rot, trans) = frames[c];
            let w = world_surfel(pl.surfels, i, rot, trans);
            match footprint(view, &w) {
                Some((zc, rect)) => {
                    let stride = pl.surfels.sh_stride();
                    let sh = &pl.surfels.sh[i * stride..(i + 1) * stride];
                    build(view, &w, sh, zc, rect)
                }
                None => Splat {
                    zc: f32::NAN,
                    ..Splat::default()
                },
            }
        })
        .collect();
    // Centre depths are ≥ NEAR > 0, so their bit patterns sort like the numbers.
    let mut keys: Vec<u64> = splats
        .par_iter()
        .enumerate()
        .with_min_len(4096)
        .filter(|(_, s)| !s.zc.is_nan())
        .map(|(g, s)| ((s.zc.to_bits() as u64) << 32) | g as u64)
        .collect();
    keys.par_sort_unstable();
    let order: Vec<u32> = keys.iter().map(|&key| key as u32).collect();
    let mut sorted_of = vec![CULLED; total];
    for (k, &g) in order.iter().enumerate() {
        sorted_of[g as usize] = k as u32;
    }
    Prepared {
        splats,
        order,
        sorted_of,
    }
}

fn finite3(v: Vec3) -> bool {
    v.is_finite()
}

/// Largest ρ a hit can have (see [`Splat::rho_max`]): the kernel's bound on |ξ|², which the
/// filter's ρ_2d obeys too.
#[inline(always)]
fn rho_max(opacity: f32) -> f32 {
    r2_max(opacity)
}

/// Centre depth and pixel rectangle, or `None` if the surfel cannot be hit: centre nearer than
/// NEAR (2DGS's frustum test), fainter than MIN_ALPHA (α ≤ opacity), degenerate or non-finite,
/// or off screen.
fn footprint(view: &View, w: &WorldSurfel) -> Option<(f32, [u32; 4])> {
    let a = w.p - view.o;
    let zc = a.dot(view.fwd);
    let [su, sv] = w.scale;
    if !(zc >= NEAR
        && w.opacity >= MIN_ALPHA
        && su > 0.0
        && sv > 0.0
        && finite3(a)
        && w.axes.is_finite()
        && su.is_finite()
        && sv.is_finite())
    {
        return None;
    }
    let c = view.project(a);
    let rect = pixel_rect(
        view,
        w.p,
        w.axes.x_axis * su,
        w.axes.y_axis * sv,
        rho_max(w.opacity),
        c,
    )?;
    Some((zc, rect))
}

fn build(view: &View, w: &WorldSurfel, sh_coeffs: &[[f32; 3]], zc: f32, rect: [u32; 4]) -> Splat {
    let a = w.p - view.o;
    let (tu, tv, n) = (w.axes.x_axis, w.axes.y_axis, w.axes.z_axis);
    let [su, sv] = w.scale;
    let wu = tu / su;
    let wv = tv / sv;
    let coeffs = |x: Vec3| [view.d0.dot(x), view.du.dot(x), view.dv.dot(x)];
    let color = splat_color(view.o, w.p, sh_coeffs).map(|x| x.max(0.0));
    let normal = n * facing_sign(n, a);
    Splat {
        hu: coeffs(wu),
        hv: coeffs(wv),
        hn: coeffs(n),
        au: a.dot(wu),
        av: a.dot(wv),
        an: a.dot(n),
        c: view.project(a),
        zc,
        opacity: w.opacity,
        rho_max: rho_max(w.opacity),
        color,
        normal: normal.to_array(),
        rect,
    }
}

/// Unclamped SH colour. The backward recomputes it bit for bit ([`sh::color_backward_f32`]),
/// so both agree on which channels the clamp at 0 cut.
fn splat_color(o: Vec3, p: Vec3, coeffs: &[[f32; 3]]) -> [f32; 3] {
    let (d, _) = sh::view_dir_f32(o.to_array(), p.to_array());
    sh::eval_f32(d, &coeffs[..coeffs.len().min(16)])
}

/// The pixels whose centres can see the surfel: the union of the projected support square
/// (`|ξ_u|, |ξ_v| ≤ √ρ_max`, clipped to depth ≥ NEAR since nearer hits are dropped) and the
/// low-pass filter's disc `2 |p − c|² ≤ ρ_max`. The square's projection contains the projected
/// disc because the clipped square is convex and lies in front of the camera.
fn pixel_rect(
    view: &View,
    p: Vec3,
    eu: Vec3,
    ev: Vec3,
    rho_max: f32,
    c: [f32; 2],
) -> Option<[u32; 4]> {
    let k = rho_max.sqrt();
    let (eu, ev) = (eu * k, ev * k);
    let corners = [p + eu + ev, p - eu + ev, p - eu - ev, p + eu - ev].map(|x| x - view.o);
    let r = (rho_max / FILTER_INV_VARIANCE).sqrt();
    let mut lo = [c[0] - r, c[1] - r];
    let mut hi = [c[0] + r, c[1] + r];
    let mut include = |q: [f32; 2]| {
        for k in 0..2 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    };
    for i in 0..4 {
        let (a, b) = (corners[i], corners[(i + 1) % 4]);
        let (za, zb) = (a.dot(view.fwd), b.dot(view.fwd));
        if za >= NEAR {
            include(view.project(a));
        }
        if (za >= NEAR) != (zb >= NEAR) {
            let s = (NEAR - za) / (zb - za);
            let q = a + s * (b - a);
            // On the near plane up to rounding; keep the depth positive for the projection.
            let q = q + view.fwd * (NEAR - q.dot(view.fwd)).max(0.0);
            include(view.project(q));
        }
    }
    if !(lo[0].is_finite() && lo[1].is_finite() && hi[0].is_finite() && hi[1].is_finite()) {
        // A corner projected to infinity or NaN: fall back to the whole image rather than lose
        // hits (only possible for degenerate inputs).
        lo = [f32::MIN, f32::MIN];
        hi = [f32::MAX, f32::MAX];
    }
    // Pixel x is seen iff its centre x + 0.5 lies in [lo, hi].
    let (w, h) = (view.width as f32, view.height as f32);
    let x0 = (lo[0] - 0.5 - RECT_MARGIN).ceil().clamp(0.0, w) as u32;
    let x1 = ((hi[0] - 0.5 + RECT_MARGIN).floor() + 1.0).clamp(0.0, w) as u32;
    let y0 = (lo[1] - 0.5 - RECT_MARGIN).ceil().clamp(0.0, h) as u32;
    let y1 = ((hi[1] - 0.5 + RECT_MARGIN).floor() + 1.0).clamp(0.0, h) as u32;
    (x0 < x1 && y0 < y1).then_some([x0, y0, x1, y1])
}

/// Depth-sorted tile lists, and for each splat where its entries are (for the backward
/// reduction).
pub(crate) struct Bins {
    /// Tile `t`'s list is `list[tile_start[t]..tile_start[t + 1]]`.
    pub tile_start: Vec<u32>,
    /// Global splat indices, each tile's front to back.
    pub list: Vec<u32>,
    /// Sorted splat `k`'s entries are `entry_of[splat_start[k]..splat_start[k + 1]]`.
    pub splat_start: Vec<u32>,
    /// Positions in `list`.
    pub entry_of: Vec<u32>,
}

impl Bins {
    pub fn tile_list(&self, tile: usize) -> &[u32] {
        &self.list[self.tile_start[tile] as usize..self.tile_start[tile + 1] as usize]
    }
}

#[inline]
fn tile_rect(s: &Splat) -> [u32; 4] {
    [
        s.rect[0] / TILE,
        s.rect[1] / TILE,
        (s.rect[2] - 1) / TILE + 1,
        (s.rect[3] - 1) / TILE + 1,
    ]
}

/// Buckets the splats into tiles in depth order, which keeps every list sorted.
pub(crate) fn bin(view: &View, splats: &[Splat], order: &[u32]) -> Bins {
    let tiles = view.tiles();
    let rects: Vec<[u32; 4]> = order
        .par_iter()
        .with_min_len(4096)
        .map(|&g| tile_rect(&splats[g as usize]))
        .collect();
    let mut tile_count = vec![0u32; tiles];
    let mut splat_start = vec![0u32; rects.len() + 1];
    for (k, &[tx0, ty0, tx1, ty1]) in rects.iter().enumerate() {
        for ty in ty0..ty1 {
            for tx in tx0..tx1 {
                tile_count[(ty * view.tiles_x + tx) as usize] += 1;
            }
        }
        splat_start[k + 1] = splat_start[k] + (tx1 - tx0) * (ty1 - ty0);
    }
    let mut tile_start = vec![0u32; tiles + 1];
    for t in 0..tiles {
        tile_start[t + 1] = tile_start[t] + tile_count[t];
    }
    let entries = tile_start[tiles] as usize;
    let mut list = vec![0u32; entries];
    let mut entry_of = vec![0u32; entries];
    let mut cursor = tile_start.clone();
    let mut j = 0;
    for (&[tx0, ty0, tx1, ty1], &g) in rects.iter().zip(order) {
        for ty in ty0..ty1 {
            for tx in tx0..tx1 {
                let t = (ty * view.tiles_x + tx) as usize;
                let pos = cursor[t];
                cursor[t] += 1;
                list[pos as usize] = g;
                entry_of[j] = pos;
                j += 1;
            }
        }
    }
    Bins {
        tile_start,
        list,
        splat_start,
        entry_of,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::SplitMix;

    /// [`hit4`] is [`hit`] on each lane, bit for bit: both passes call `hit4`, and the splat's
    /// figures (and the slow reference's tolerances in `tests/splat.rs`) were set by `hit`.
    /// Random splats whose pixels land inside, at the edge of and outside their support, rays
    /// nearly in their plane, and lanes left out of `live`.
    #[test]
    fn hit4_is_hit_on_every_lane() {
        let mut rng = SplitMix(46);
        let (mut hits, mut misses) = (0, 0);
        for case in 0..20_000 {
            let mut r = |lo: f32, hi: f32| rng.range(lo, hi);
            let s = Splat {
                hu: [r(-2.0, 2.0), r(-0.2, 0.2), r(-0.2, 0.2)],
                hv: [r(-2.0, 2.0), r(-0.2, 0.2), r(-0.2, 0.2)],
                // Every 16th case nearly edge-on: d·n crosses 0 within the row.
                hn: if case % 16 == 0 {
                    [r(-0.01, 0.01), r(-1e-3, 1e-3), r(-1e-3, 1e-3)]
                } else {
                    [r(0.2, 1.5), r(-0.01, 0.01), r(-0.01, 0.01)]
                },
                au: r(-3.0, 3.0),
                av: r(-3.0, 3.0),
                an: r(-2.0, 2.0),
                c: [r(0.0, 16.0), r(0.0, 16.0)],
                zc: r(-0.5, 4.0),
                opacity: r(0.0, 1.0),
                rho_max: r(0.0, 12.0),
                ..Splat::default()
            };
            let v = (rng.next_u64() % 16) as f32 + 0.5;
            let live = (rng.next_u64() % 16) as u32;
            let cols = [0, 1, 2, 3].map(|_| (rng.next_u64() % 16) as f32 + 0.5);
            let got = hit4(&s, Vec4::from_array(cols), v, live);
            let got = [0, 1, 2, 3].map(|l| got.get(l));
            for lane in 0..4 {
                let want = if live & (1 << lane) != 0 {
                    hit(&s, cols[lane], v)
                } else {
                    None
                };
                match (want, got[lane]) {
                    (None, None) => misses += 1,
                    (Some(a), Some(b)) => {
                        hits += 1;
                        let bits = |h: Hit| {
                            [
                                h.alpha, h.g, h.z, h.t, h.den, h.du, h.dv, h.xu, h.xv, h.dx, h.dy,
                            ]
                            .map(f32::to_bits)
                        };
                        assert_eq!(bits(a), bits(b), "case {case} lane {lane}");
                        assert_eq!((a.plane, a.clamped), (b.plane, b.clamped), "case {case}");
                    }
                    (a, b) => panic!("case {case} lane {lane}: hit {a:?}, hit4 {b:?}"),
                }
            }
        }
        // Both outcomes well represented, so neither branch is checked vacuously.
        assert!(
            hits > 5_000 && misses > 5_000,
            "{hits} hits, {misses} misses"
        );
    }
}
