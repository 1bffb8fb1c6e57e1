//! One surfel as the hit test sees it (eq. gaussian-response), and its bounds.

use crate::kernel::r2_max;
#[cfg(test)]
use crate::kernel::response;
use crate::scene::quat_axes;
use glam::{Mat4, Vec3, Vec4};

/// Everything the hit test reads, precomputed and packed into one cache line: a traversal
/// touches surfels in leaf order, so one line per test beats gathering from separate arrays.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(64))]
pub(crate) struct HitSurfel {
    /// Centre μ.
    pub mu: [f32; 3],
    /// Opacity α.
    pub alpha: f32,
    /// Unit normal n (third column of R(q)).
    pub n: [f32; 3],
    /// Largest |ξ|² that can pass both the support and the opacity threshold
    /// ([`crate::kernel::r2_max`]); the exact test in `hit` decides.
    pub r2_max: f32,
    /// t_u / s_u: (x − μ)·u is ξ_u.
    pub u: [f32; 3],
    /// The surfel's index in its component (also in `Blas::index`): the hit's tie-break key,
    /// read from the line the hit test has just loaded rather than from a second array.
    pub index: u32,
    /// t_v / s_v.
    pub v: [f32; 3],
    _pad1: f32,
}

impl HitSurfel {
    pub fn new(
        position: [f32; 3],
        rotation: [f32; 4],
        scale: [f32; 2],
        opacity: f32,
        index: u32,
    ) -> Self {
        let [tu, tv, n] = quat_axes(rotation);
        let u = Vec3::from_array(tu) / scale[0];
        let v = Vec3::from_array(tv) / scale[1];
        HitSurfel {
            mu: position,
            alpha: opacity,
            n,
            r2_max: r2_max(opacity),
            u: u.to_array(),
            index,
            v: v.to_array(),
            _pad1: 0.0,
        }
    }

    /// The scalar reference [`hit4`] is tested against, one lane of it. The hit of the ray
    /// `o + t d` with `t` in `[t_lo, t_hi]` (inclusive; callers apply their
    /// own strictness and tie-breaks): `(t, α_eff)`, or `None` when the plane is missed, the
    /// hit lies outside the support or is fainter than [`super::MIN_ALPHA`]. Never yields NaN: a ray in
    /// the plane gives t = NaN or ±∞, which every comparison below rejects.
    #[cfg(test)]
    pub fn hit(&self, o: Vec3, d: Vec3, t_lo: f32, t_hi: f32) -> Option<(f32, f32)> {
        let mu = Vec3::from_array(self.mu);
        let n = Vec3::from_array(self.n);
        let om = o - mu;
        let t = -om.dot(n) / d.dot(n);
        if !(t >= t_lo && t <= t_hi && t < f32::INFINITY) {
            return None;
        }
        let p = om + t * d;
        let xu = p.dot(Vec3::from_array(self.u));
        let xv = p.dot(Vec3::from_array(self.v));
        let r2 = xu * xu + xv * xv;
        // Written so that a NaN r² (from a degenerate ray) is rejected too.
        if r2.is_nan() || r2 > self.r2_max {
            return None;
        }
        // eq. gaussian-response, capped and thresholded as the rasteriser does.
        response(self.alpha, r2).map(|r| (t, r.alpha))
    }
}

/// [`HitSurfel::hit`] for up to four surfels at once, lane by lane the same IEEE operations in
/// the same order (so the same bits): the lanes in `live` whose plane hit lies in `[t_lo, t_hi]`
/// and inside the disc |ξ|² ≤ r2_max, with their `t` and |ξ|². The caller applies
/// [`crate::kernel::response`] to the lanes kept. One test for the leaves a BVH node lets the
/// ray into, rather than one branchy test per surfel (the hit test rejects over half of what it
/// sees, at one of three branches). Measured against the scalar test, alternating
/// (`cargo bench --bench trace`): composited camera rays on the 200k room +9 %, the learned
/// scene's render +5-8 %.
#[inline(always)]
pub(crate) fn hit4(
    s: [&HitSurfel; 4],
    live: u32,
    o: Vec3,
    d: Vec3,
    t_lo: f32,
    t_hi: f32,
) -> (u32, Vec4, Vec4) {
    // Each surfel is four 16-byte quads (μ|α, n|r2_max, u|index, v|pad): four of one quad,
    // transposed, are its x, y, z and w lanes.
    let lanes = |quad: fn(&HitSurfel) -> Vec4| {
        let m = Mat4::from_cols(quad(s[0]), quad(s[1]), quad(s[2]), quad(s[3])).transpose();
        (m.x_axis, m.y_axis, m.z_axis, m.w_axis)
    };
    let (mx, my, mz, _) = lanes(|h| Vec4::new(h.mu[0], h.mu[1], h.mu[2], h.alpha));
    let (nx, ny, nz, r2_max) = lanes(|h| Vec4::new(h.n[0], h.n[1], h.n[2], h.r2_max));
    let (omx, omy, omz) = (
        Vec4::splat(o.x) - mx,
        Vec4::splat(o.y) - my,
        Vec4::splat(o.z) - mz,
    );
    let (dx, dy, dz) = (Vec4::splat(d.x), Vec4::splat(d.y), Vec4::splat(d.z));
    // Vec3::dot is (x·x' + y·y') + z·z'.
    let t = -(omx * nx + omy * ny + omz * nz) / (dx * nx + dy * ny + dz * nz);
    let in_range =
        t.cmpge(Vec4::splat(t_lo)) & t.cmple(Vec4::splat(t_hi)) & t.cmplt(Vec4::INFINITY);
    let mut mask = live & in_range.bitmask();
    if mask == 0 {
        return (0, t, Vec4::ZERO);
    }
    let (px, py, pz) = (omx + t * dx, omy + t * dy, omz + t * dz);
    let (ux, uy, uz, _) = lanes(|h| Vec4::new(h.u[0], h.u[1], h.u[2], 0.0));
    let (vx, vy, vz, _) = lanes(|h| Vec4::new(h.v[0], h.v[1], h.v[2], 0.0));
    let xu = px * ux + py * uy + pz * uz;
    let xv = px * vx + py * vy + pz * vz;
    let r2 = xu * xu + xv * xv;
    // A NaN r² fails `<=`, as it fails the scalar test.
    mask &= r2.cmple(r2_max).bitmask();
    (mask, t, r2)
}

/// Axis-aligned bounds of the part of a surfel that can be hit: the disc |ξ|² ≤ r2_max(α)
/// ([`crate::kernel::r2_max`]: the support, |ξ| ≤ CUTOFF, shrunk to where α·exp(−½|ξ|²) can still
/// reach MIN_ALPHA). Along world axis k the ellipse with semi-axes r·s_u·t_u and r·s_v·t_v
/// reaches ±r·sqrt((s_u t_u\[k\])² + (s_v t_v\[k\])²). A faint surfel's box is smaller than its
/// support's (α = 0.05: r = 2.3 rather than 3, a 43 % smaller cross-section), and a learned
/// scene has many: the hit test rejects everything outside r2_max anyway, so the hits are the
/// same and fewer leaves are entered.
pub fn surfel_bounds(
    position: [f32; 3],
    rotation: [f32; 4],
    scale: [f32; 2],
    opacity: f32,
) -> ([f32; 3], [f32; 3]) {
    let [tu, tv, _] = quat_axes(rotation);
    // An opacity that can never reach MIN_ALPHA gives a point: it is never hit.
    let radius = r2_max(opacity).max(0.0).sqrt();
    let mut lo = [0.0; 3];
    let mut hi = [0.0; 3];
    for k in 0..3 {
        let a = scale[0] * tu[k];
        let b = scale[1] * tv[k];
        let r = radius * (a * a + b * b).sqrt();
        lo[k] = position[k] - r;
        hi[k] = position[k] + r;
    }
    (lo, hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `hit4` keeps exactly the lanes `hit` keeps, with the same t and the same response, bit
    /// for bit: random surfels and rays aimed near them, lanes switched off, rays in the plane.
    #[test]
    fn hit4_is_hit_four_times() {
        use crate::kernel::response;
        let mut rng = SplitMix(21);
        let (mut kept, mut dropped) = (0, 0);
        for case in 0..3000 {
            let surfels: Vec<HitSurfel> = (0..4)
                .map(|i| {
                    let q = rotation(&mut rng);
                    let mu = point(&mut rng, 0.3);
                    let scale = [rng.range(0.02, 0.4), rng.range(0.02, 0.4)];
                    HitSurfel::new(mu, q, scale, rng.range(0.0, 1.0), i)
                })
                .collect();
            let o = Vec3::new(
                rng.range(-2.0, 2.0),
                rng.range(-2.0, 2.0),
                rng.range(-2.0, 2.0),
            );
            let mut d = (Vec3::new(
                rng.range(-0.3, 0.3),
                rng.range(-0.3, 0.3),
                rng.range(-0.3, 0.3),
            ) - o)
                .normalize();
            if case % 50 == 0 {
                // In the first surfel's plane.
                let n = Vec3::from_array(surfels[0].n);
                d = (d - d.dot(n) * n).normalize();
            }
            let (t_lo, t_hi) = if case % 3 == 0 {
                (0.0, f32::INFINITY)
            } else {
                (rng.range(0.0, 2.0), rng.range(2.0, 4.0))
            };
            let live = (case % 16) as u32;
            let refs = [&surfels[0], &surfels[1], &surfels[2], &surfels[3]];
            let (mask, t, r2) = hit4(refs, live, o, d, t_lo, t_hi);
            for (l, s) in surfels.iter().enumerate() {
                let want = if live & (1 << l) != 0 {
                    s.hit(o, d, t_lo, t_hi)
                } else {
                    None
                };
                let got = (mask & (1 << l) != 0)
                    .then(|| response(s.alpha, r2[l]).map(|r| (t[l], r.alpha)))
                    .flatten();
                assert_eq!(
                    got.map(|(t, a)| (t.to_bits(), a.to_bits())),
                    want.map(|(t, a)| (t.to_bits(), a.to_bits())),
                    "case {case} lane {l}"
                );
                kept += want.is_some() as usize;
                dropped += (live & (1 << l) != 0 && want.is_none()) as usize;
            }
        }
        assert!(
            kept > 500 && dropped > 500,
            "both outcomes: {kept} kept, {dropped} dropped"
        );
    }
    use crate::kernel::MIN_ALPHA;
    use crate::scene::synthetic::SplitMix;

    fn rotation(rng: &mut SplitMix) -> [f32; 4] {
        let mut angle = || rng.range(-3.0, 3.0);
        let (a, b, c) = (angle(), angle(), angle());
        glam::Quat::from_euler(glam::EulerRot::XYZ, a, b, c).to_array()
    }

    /// A point in the cube [−r, r]³.
    fn point(rng: &mut SplitMix, r: f32) -> [f32; 3] {
        [rng.range(-r, r), rng.range(-r, r), rng.range(-r, r)]
    }

    /// Every hit the exact test keeps lies in the box `surfel_bounds` gives (the BVH never
    /// prunes a hit), for opacities from barely visible to capped, including hits aimed at the
    /// edge of the hittable disc, where the box is tight.
    #[test]
    fn bounds_hold_every_kept_hit() {
        let mut rng = SplitMix(3);
        let mut kept = 0;
        for _ in 0..2000 {
            let q = rotation(&mut rng);
            let mu = point(&mut rng, 1.0);
            let scale = [rng.range(0.01, 0.5), rng.range(0.01, 0.5)];
            let opacity = rng.range(MIN_ALPHA * 0.9, 1.0);
            let s = HitSurfel::new(mu, q, scale, opacity, 0);
            let (lo, hi) = surfel_bounds(mu, q, scale, opacity);
            // Aim at a point of the plane at radius r·(0.9..1.0) of the hittable disc.
            let [tu, tv, n] = quat_axes(q);
            let r = s.r2_max.max(0.0).sqrt() * rng.range(0.9, 1.0);
            let phi = rng.range(0.0, std::f32::consts::TAU);
            let target = Vec3::from_array(mu)
                + r * phi.cos() * scale[0] * Vec3::from_array(tu)
                + r * phi.sin() * scale[1] * Vec3::from_array(tv);
            let from = target
                + Vec3::from_array(n) * rng.range(0.2, 2.0)
                + Vec3::new(
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                );
            let d = (target - from).normalize();
            if let Some((t, _)) = s.hit(from, d, 0.0, f32::INFINITY) {
                kept += 1;
                let x = from + t * d;
                for k in 0..3 {
                    let slack = 1e-5 * (1.0 + x[k].abs());
                    assert!(
                        x[k] >= lo[k] - slack && x[k] <= hi[k] + slack,
                        "hit {x} outside {lo:?}..{hi:?} (opacity {opacity})"
                    );
                }
            }
        }
        assert!(kept > 500, "the rays should mostly hit: {kept}");
        // Too faint to ever be kept: a point.
        let (lo, hi) = surfel_bounds([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], [1.0, 1.0], 0.0);
        assert_eq!((lo, hi), ([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]));
    }
}
