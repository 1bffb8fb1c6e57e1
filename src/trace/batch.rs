//! A sorted batch of the nearest hits along a ray: the fixed-size buffer one traversal fills.

use super::{BATCH, T_MIN};

/// A hit waiting to be composited. `key` = component << 32 | surfel index (the component's own
/// numbering) breaks ties in `t`, so (t, key) orders all hits totally and a batch can resume
/// exactly after the last one it composited.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Hit {
    pub t: f32,
    pub alpha: f32,
    pub key: u64,
    /// Index into the component's leaf-ordered hit data.
    pub slot: u32,
}

#[inline(always)]
pub(crate) fn before(a: (f32, u64), b: (f32, u64)) -> bool {
    a.0 < b.0 || (a.0 == b.0 && a.1 < b.1)
}

/// The up to [`BATCH`] nearest hits accepted so far, sorted by (t, key). Its `upper` bound only
/// shrinks: a new hit must come before it, and the BVH prunes nodes beyond `upper.0`.
pub(crate) struct HitBatch {
    hits: [Hit; BATCH],
    len: usize,
    /// Transmittance behind all buffered hits, including what earlier batches absorbed. Kept by
    /// multiplication so an insert costs O(1) until it falls below [`T_MIN`]; only then is the
    /// exact prefix walked to find where the ray ends.
    behind: f32,
    /// The buffer ends at the hit that drops the transmittance below [`T_MIN`].
    cut: bool,
    upper: (f32, u64),
    carry: f32,
}

impl HitBatch {
    /// An empty batch for hits before `t_max` (exclusive), behind transmittance `carry`.
    #[inline]
    pub fn new(carry: f32, t_max: f32) -> Self {
        HitBatch {
            hits: [Hit::default(); BATCH],
            len: 0,
            behind: carry,
            cut: false,
            // Key 0 is the smallest, so (t, key) < (t_max, 0) means t < t_max.
            upper: (t_max, 0),
            carry,
        }
    }

    /// Where the BVH may stop looking (inclusive: ties at this t may still be accepted).
    #[inline(always)]
    pub fn bound(&self) -> f32 {
        self.upper.0
    }

    #[inline(always)]
    pub fn accepts(&self, t: f32, key: u64) -> bool {
        before((t, key), self.upper)
    }

    /// Inserts an accepted hit, dropping the farthest one when full, and re-derives the bound.
    #[inline]
    pub fn insert(&mut self, hit: Hit) {
        debug_assert!(self.accepts(hit.t, hit.key));
        let mut p = self.len;
        while p > 0 && before((hit.t, hit.key), (self.hits[p - 1].t, self.hits[p - 1].key)) {
            p -= 1;
        }
        if self.len == BATCH {
            // The farthest hit leaves: recompute rather than divide, to stay exact.
            self.hits.copy_within(p..BATCH - 1, p + 1);
            self.hits[p] = hit;
            self.behind = self
                .hits
                .iter()
                .fold(self.carry, |tr, h| tr * (1.0 - h.alpha));
        } else {
            self.hits.copy_within(p..self.len, p + 1);
            self.hits[p] = hit;
            self.len += 1;
            self.behind *= 1.0 - hit.alpha;
        }
        // Evicting the hit that ended the ray can leave the rest above T_MIN again.
        self.cut = false;
        if self.behind < T_MIN {
            // The first hit that drops the transmittance below T_MIN ends the ray: everything
            // after it is discarded and nothing behind it is looked for.
            let mut tr = self.carry;
            for i in 0..self.len {
                tr *= 1.0 - self.hits[i].alpha;
                if tr < T_MIN {
                    self.len = i + 1;
                    self.cut = true;
                    break;
                }
            }
            // Exact now, whether or not the rounding of the running product was.
            self.behind = tr;
        }
        if self.cut || self.len == BATCH {
            let last = self.hits[self.len - 1];
            self.upper = (last.t, last.key);
        }
    }

    /// The hits in order with their weights w = T·α (eq. surface-record).
    #[inline]
    pub fn weighted(&self) -> impl Iterator<Item = (f32, &Hit)> {
        self.hits[..self.len].iter().scan(self.carry, |tr, h| {
            let w = *tr * h.alpha;
            *tr *= 1.0 - h.alpha;
            Some((w, h))
        })
    }

    /// Whether this batch ends the ray: either the transmittance fell below [`T_MIN`] or the
    /// buffer did not fill, so there is nothing more in range.
    #[inline]
    pub fn finishes(&self) -> bool {
        self.cut || self.len < BATCH
    }

    /// Where the next batch starts (exclusive) and the transmittance it starts behind.
    #[inline]
    pub fn resume(&self) -> ((f32, u64), f32) {
        let last = self.hits[self.len - 1];
        ((last.t, last.key), self.behind)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hit(t: f32, key: u64, alpha: f32) -> Hit {
        Hit {
            t,
            alpha,
            key,
            slot: 0,
        }
    }

    #[test]
    fn keeps_the_nearest_sorted_and_bounds_by_the_last() {
        let mut b = HitBatch::new(1.0, f32::INFINITY);
        for i in (0..BATCH as u64 + 10).rev() {
            let h = hit(i as f32 * 0.5, i, 0.1);
            if b.accepts(h.t, h.key) {
                b.insert(h);
            }
        }
        let ts: Vec<f32> = b.weighted().map(|(_, h)| h.t).collect();
        assert_eq!(ts.len(), BATCH);
        assert!(ts.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(b.bound(), (BATCH - 1) as f32 * 0.5);
        assert!(!b.finishes());
        let (after, tr) = b.resume();
        assert_eq!(after, ((BATCH - 1) as f32 * 0.5, BATCH as u64 - 1));
        assert!((tr - 0.9f32.powi(BATCH as i32)).abs() < 1e-6);
    }

    #[test]
    fn cuts_at_negligible_transmittance_and_ties_break_by_key() {
        let mut b = HitBatch::new(1.0, 10.0);
        for key in [5u64, 3, 9, 1, 7] {
            b.insert(hit(2.0, key, 0.95));
        }
        // 0.05³ = 1.25e-4 is not below T_MIN; 0.05⁴ is.
        let keys: Vec<u64> = b.weighted().map(|(_, h)| h.key).collect();
        assert_eq!(keys, vec![1, 3, 5, 7]);
        assert!(b.finishes());
        assert!(!b.accepts(2.0, 8));
        assert!(b.accepts(2.0, 6));
    }
}
