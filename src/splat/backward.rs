//! The backward pass. Per tile, back to front from each pixel's last contributor: with
//! `T_j = T_{j+1} / (1 − α_j)` and `B_j` the composite of everything behind hit j (seen from
//! it), `dL/dα_j = T_j (g·f_j − B_{j+1})` and `B_j = α_j g·f_j + (1 − α_j) B_{j+1}`, where
//! `f_j` stacks the hit's colour, 1 (opacity), depth and normal and `g` the pixel's upstream
//! gradient. Each (tile, surfel) pair sums its pixels into one slot of a buffer laid out like
//! the tile lists. A second parallel pass sums each splat's slots, walking the splats in depth
//! order so that every tile's slots are read forwards; a third, in input order, carries each
//! sum through the projection to the surfel's parameters and its placement.

use super::forward::{clip, row_bits, tile_pixels, PREFETCH_AHEAD};
use super::project::prefetch;
use super::project::{facing_sign, placement_frame, row_hits, world_surfel, CULLED};
use super::{sh, Forward, Gradients, ImageGrad, SurfelGrads, FILTER_INV_VARIANCE};
use super::{TILE, TILE_PIXELS};
use crate::kernel::composite::Back;
use crate::kernel::quat_grad;
use crate::scene::transform::TransformGrad;
use glam::{Mat3, Vec3};
use rayon::prelude::*;

/// Gradient slots per (tile, surfel): with respect to the `project::Splat` quantities.
const NG: usize = 22;
const G_HU: usize = 0; // 3: hu
const G_HV: usize = 3; // 3: hv
const G_HN: usize = 6; // 3: hn
const G_AU: usize = 9;
const G_AV: usize = 10;
const G_AN: usize = 11;
const G_C: usize = 12; // 2: projected centre
const G_ZC: usize = 14;
const G_OPACITY: usize = 15;
const G_COLOR: usize = 16; // 3
const G_NORMAL: usize = 19; // 3

/// Upstream gradient of one pixel, with the depth division folded in: for D = S / A,
/// dL/dS = g_D / A and dL/dA gains −g_D D / A.
#[derive(Clone, Copy, Debug, Default)]
struct PixelGrad {
    color: [f32; 3],
    alpha: f32,
    depth_sum: f32,
    median: f32,
    normal: [f32; 3],
}

pub(crate) fn backward(f: &Forward, grad: &ImageGrad) -> Gradients {
    let view = &f.view;
    let tiles = view.tiles();
    let mut slots = vec![[0.0f32; NG]; f.bins.list.len()];
    let mut per_tile: Vec<&mut [[f32; NG]]> = Vec::with_capacity(tiles);
    let mut rest = &mut slots[..];
    for t in 0..tiles {
        let n = (f.bins.tile_start[t + 1] - f.bins.tile_start[t]) as usize;
        let (head, tail) = rest.split_at_mut(n);
        per_tile.push(head);
        rest = tail;
    }
    per_tile
        .into_par_iter()
        .enumerate()
        .for_each(|(tile, out)| backward_tile(f, grad, tile, out));

    let bins = &f.bins;
    // Each drawn splat's slots summed in a fixed order (its tiles row-major, as `bin` lists
    // them). Walking the splats in sorted order reads every tile's slice of `slots` forwards;
    // the surfel loop below, in input order, then reads one sum per surfel.
    const SUM_CHUNK: usize = 2048;
    let mut sums = vec![[0.0f32; NG]; f.prepared.order.len()];
    sums.par_chunks_mut(SUM_CHUNK)
        .enumerate()
        .for_each(|(chunk, out)| {
            for (j, g) in out.iter_mut().enumerate() {
                let k = chunk * SUM_CHUNK + j;
                let entries = bins.splat_start[k] as usize..bins.splat_start[k + 1] as usize;
                for &e in &bins.entry_of[entries] {
                    for (a, b) in g.iter_mut().zip(&slots[e as usize]) {
                        *a += b;
                    }
                }
            }
        });
    drop(slots);

    let mut out = Gradients::default();
    for (c, pl) in f.components.iter().enumerate() {
        let s = pl.surfels;
        let n = s.len();
        let stride = s.sh_stride();
        let mut g = SurfelGrads::zeros(n, stride);
        let (rot, trans) = placement_frame(pl);
        let base = f.offsets[c];
        const CHUNK: usize = 1024;
        // Per chunk: the placement gradient's partial sum, reduced in chunk order below so the
        // result does not depend on how rayon splits the work.
        let partial: Vec<[f32; 6]> = g
            .position
            .par_chunks_mut(CHUNK)
            .zip(g.rotation.par_chunks_mut(CHUNK))
            .zip(g.scale.par_chunks_mut(CHUNK))
            .zip(g.opacity.par_chunks_mut(CHUNK))
            .zip(g.sh.par_chunks_mut(CHUNK * stride.max(1)))
            .enumerate()
            .map(|(chunk, ((((gp, gq), gs), go), gsh))| {
                let mut acc = [0.0f32; 6];
                let sorted_of = &f.prepared.sorted_of[base + chunk * CHUNK..][..gp.len()];
                for j in 0..gp.len() {
                    let i = chunk * CHUNK + j;
                    // The sums are read in a random order: ask for them ahead.
                    if let Some(&ahead) = sorted_of.get(j + SUM_AHEAD) {
                        if ahead != CULLED {
                            prefetch_sum(&sums, ahead as usize);
                        }
                    }
                    let k = sorted_of[j];
                    if k == CULLED {
                        continue;
                    }
                    let sg = &sums[k as usize];
                    if sg.iter().all(|x| *x == 0.0) {
                        continue;
                    }
                    let w = world_surfel(s, i, rot, trans);
                    let r = surfel_grad(
                        f,
                        &w,
                        s.rotation[i],
                        &s.sh[i * stride..(i + 1) * stride],
                        rot,
                        trans,
                        sg,
                        &mut gsh[j * stride..(j + 1) * stride],
                    );
                    gp[j] = r.position;
                    gq[j] = r.rotation;
                    gs[j] = r.scale;
                    go[j] = r.opacity;
                    for (a, t) in acc.iter_mut().zip(r.transform) {
                        *a += t;
                    }
                }
                acc
            })
            .collect();
        let mut tg = [0.0f32; 6];
        for p in partial {
            for k in 0..6 {
                tg[k] += p[k];
            }
        }
        out.surfels.push(g);
        out.transforms.push(TransformGrad {
            translation: [tg[0], tg[1], tg[2]],
            rotation: [tg[3], tg[4], tg[5]],
        });
    }
    out
}

/// How many surfels ahead the surfel loop prefetches its gradient sums.
const SUM_AHEAD: usize = 8;

/// Asks for the (up to two) cache lines of `sums[k]`.
#[inline(always)]
fn prefetch_sum(sums: &[[f32; NG]], k: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(s) = sums.get(k) {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let p = s.as_ptr() as *const i8;
        // SAFETY: prefetching is a hint that never faults, and `p` points into a live slice.
        unsafe {
            _mm_prefetch(p, _MM_HINT_T0);
            _mm_prefetch(p.add(NG * 4 - 1), _MM_HINT_T0);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (sums, k);
}

fn backward_tile(f: &Forward, grad: &ImageGrad, tile: usize, slots: &mut [[f32; NG]]) {
    let view = &f.view;
    let list = f.bins.tile_list(tile);
    let states = &f.pixels[tile * TILE_PIXELS..(tile + 1) * TILE_PIXELS];
    let bounds = tile_pixels(view, tile);
    let (x0, y0, x1, y1) = bounds;

    let mut pg = [PixelGrad::default(); TILE_PIXELS];
    // Transmittance in front of the current hit, and B: the composite behind it.
    let mut trans = [0.0f32; TILE_PIXELS];
    let mut behind = [0.0f32; TILE_PIXELS];
    let mut max_last = 0;
    for y in y0..y1 {
        for x in x0..x1 {
            let p = ((y - y0) * TILE + (x - x0)) as usize;
            let i = (y * view.width + x) as usize;
            let a = f.image.alpha[i];
            let (gd, d) = (grad.depth[i], f.image.depth[i]);
            let (depth_sum, alpha_extra) = if a > 0.0 {
                (gd / a, -gd * d / a)
            } else {
                (0.0, 0.0)
            };
            pg[p] = PixelGrad {
                color: grad.color[i],
                alpha: grad.alpha[i] + alpha_extra,
                depth_sum,
                median: grad.median_depth[i],
                normal: grad.normal[i],
            };
            trans[p] = states[p].t;
            max_last = max_last.max(states[p].last);
        }
    }

    // Pixels in order of decreasing last contributor: pixel p joins the walk (its bit in
    // `open`, per tile row) once k < last(p).
    let mut order: Vec<u16> = (0..TILE_PIXELS as u16)
        .filter(|&p| states[p as usize].last > 0)
        .collect();
    order.sort_unstable_by_key(|&p| std::cmp::Reverse(states[p as usize].last));
    let mut joined = 0;
    let mut open = [0u32; TILE as usize];
    for k in (0..max_last as usize).rev() {
        while let Some(&p) = order.get(joined) {
            if states[p as usize].last as usize <= k {
                break;
            }
            open[p as usize / TILE as usize] |= 1 << (p as usize % TILE as usize);
            joined += 1;
        }
        if k >= PREFETCH_AHEAD {
            prefetch(&f.prepared.splats, list[k - PREFETCH_AHEAD] as usize);
        }
        let s = &f.prepared.splats[list[k] as usize];
        let (sx0, sy0, sx1, sy1) = clip(s, bounds);
        let cols = row_bits(x0, sx0, sx1);
        let mut g = [0.0f32; NG];
        for y in sy0..sy1 {
            let v = y as f32 + 0.5;
            let r = (y - y0) as usize;
            for (bit, u, h) in row_hits(s, x0, v, open[r] & cols) {
                let p = r * TILE as usize + bit as usize;
                let q = &pg[p];
                let gdot = q.color[0] * s.color[0]
                    + q.color[1] * s.color[1]
                    + q.color[2] * s.color[2]
                    + q.alpha
                    + q.depth_sum * h.z
                    + q.normal[0] * s.normal[0]
                    + q.normal[1] * s.normal[1]
                    + q.normal[2] * s.normal[2];
                let mut back = Back {
                    trans: trans[p],
                    behind: behind[p],
                };
                let (w, d_alpha) = back.step(h.alpha, gdot);
                (trans[p], behind[p]) = (back.trans, back.behind);
                for c in 0..3 {
                    g[G_COLOR + c] += w * q.color[c];
                    g[G_NORMAL + c] += w * q.normal[c];
                }
                let mut gz = w * q.depth_sum;
                if states[p].median == k as u32 + 1 {
                    gz += q.median;
                }
                let mut g_rho = 0.0;
                if !h.clamped {
                    g[G_OPACITY] += d_alpha * h.g;
                    g_rho = -0.5 * h.alpha * d_alpha;
                }
                if h.plane {
                    // ρ = ξ_u² + ξ_v², ξ = t (d·w) − a·w, t = a·n / d·n, z = t.
                    let g_xu = 2.0 * g_rho * h.xu;
                    let g_xv = 2.0 * g_rho * h.xv;
                    let g_t = gz + g_xu * h.du + g_xv * h.dv;
                    let (g_du, g_dv) = (g_xu * h.t, g_xv * h.t);
                    let g_den = -g_t * h.t / h.den;
                    let uv = [1.0, u, v];
                    for j in 0..3 {
                        g[G_HU + j] += g_du * uv[j];
                        g[G_HV + j] += g_dv * uv[j];
                        g[G_HN + j] += g_den * uv[j];
                    }
                    g[G_AU] -= g_xu;
                    g[G_AV] -= g_xv;
                    g[G_AN] += g_t / h.den;
                } else {
                    // ρ = FILTER_INV_VARIANCE |c − p|², z = centre depth.
                    g[G_C] += 2.0 * FILTER_INV_VARIANCE * g_rho * h.dx;
                    g[G_C + 1] += 2.0 * FILTER_INV_VARIANCE * g_rho * h.dy;
                    g[G_ZC] += gz;
                }
            }
        }
        slots[k] = g;
    }
}

/// One surfel's gradients in its component's frame, and its contribution to the placement's.
struct OneGrad {
    position: [f32; 3],
    rotation: [f32; 4],
    scale: [f32; 2],
    opacity: f32,
    /// dL/dδ, dL/dω.
    transform: [f32; 6],
}

/// Carries the `Splat`-level gradient `g` back to the surfel's parameters.
#[allow(clippy::too_many_arguments)]
fn surfel_grad(
    f: &Forward,
    w: &super::project::WorldSurfel,
    q_raw: [f32; 4],
    sh_coeffs: &[[f32; 3]],
    rot: Mat3,
    trans: Vec3,
    g: &[f32; NG],
    d_sh: &mut [[f32; 3]],
) -> OneGrad {
    let view = &f.view;
    let v3 = |k: usize| Vec3::new(g[k], g[k + 1], g[k + 2]);
    let a = w.p - view.o;
    let (tu, tv, n) = (w.axes.x_axis, w.axes.y_axis, w.axes.z_axis);
    let [su, sv] = w.scale;
    let (wu, wv) = (tu / su, tv / sv);
    let ray = |k: usize| view.d0 * g[k] + view.du * g[k + 1] + view.dv * g[k + 2];

    // hu = (d0, du, dv)·w_u, au = a·w_u; likewise v and n.
    let g_wu = ray(G_HU) + a * g[G_AU];
    let g_wv = ray(G_HV) + a * g[G_AV];
    let g_n = ray(G_HN) + a * g[G_AN] + v3(G_NORMAL) * facing_sign(n, a);
    let mut g_a = wu * g[G_AU] + wv * g[G_AV] + n * g[G_AN] + view.fwd * g[G_ZC];

    // c = (cx + fx (a·r) / z, cy − fy (a·u) / z), z = a·fwd.
    let z = a.dot(view.fwd);
    let (ar, au) = (a.dot(view.right), a.dot(view.up));
    let dcx = view.fx * (view.right / z - view.fwd * (ar / (z * z)));
    let dcy = -view.fy * (view.up / z - view.fwd * (au / (z * z)));
    g_a += dcx * g[G_C] + dcy * g[G_C + 1];

    // Colour: SH coefficients, and the view direction's dependence on the centre.
    let (dir, len) = sh::view_dir_f32(view.o.to_array(), w.p.to_array());
    let d_color = [g[G_COLOR], g[G_COLOR + 1], g[G_COLOR + 2]];
    let sh_coeffs = &sh_coeffs[..sh_coeffs.len().min(16)];
    let (_, g_a_sh) = sh::color_backward_f32(dir, len, sh_coeffs, d_color, d_sh);
    g_a += Vec3::from_array(g_a_sh);

    // w_u = t_u / s_u.
    let g_tu = g_wu / su;
    let g_tv = g_wv / sv;
    let g_su = -g_wu.dot(wu) / su;
    let g_sv = -g_wv.dot(wv) / sv;

    // World → component frame: p_w = R_T p + t, R_w = R_T R_o.
    let rt = rot.transpose();
    let g_ro = Mat3::from_cols(rt * g_tu, rt * g_tv, rt * g_n);
    let rotation = quat_grad(q_raw, g_ro);
    // Placement: δp_w = ω × (p_w − t) + δ, δ(col_k) = ω × col_k.
    let omega = (w.p - trans).cross(g_a) + tu.cross(g_tu) + tv.cross(g_tv) + n.cross(g_n);
    OneGrad {
        position: (rt * g_a).to_array(),
        rotation,
        scale: [g_su, g_sv],
        opacity: g[G_OPACITY],
        transform: [g_a.x, g_a.y, g_a.z, omega.x, omega.y, omega.z],
    }
}
