//! A sorted batch of the nearest hits along a ray: the fixed-size buffer one traversal fills.

use super::{BATCH, T_MIN};

/// Below this, a running product of (1 − α) kept by multiplying and dividing in arrival order is
/// surely below [`T_MIN`] in the exact sorted order too. The two are products of the same
/// factors, rounded differently: the exact one by at most [`BATCH`] roundings, the running one by
/// at most [`DRIFT_MAX`] + [`BATCH`] since it was last exact (each 2⁻²⁴ relative at most, a
/// positive product's relative errors add to first order): (1024 + 2·128)·2⁻²⁴ ≈ 7.6·10⁻⁵,
/// under the margin of 1.5·10⁻⁴.
const CUT_SURELY: f32 = T_MIN * (1.0 - 1.5e-4);

/// Multiplications and divisions of the running product after which it is derived exactly
/// again (see [`CUT_SURELY`]).
const DRIFT_MAX: u32 = 1024;

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
    /// Transmittance in front of this hit, kept by the batch (in what was padding).
    front: f32,
}

impl Hit {
    #[inline(always)]
    pub fn new(t: f32, alpha: f32, key: u64, slot: u32) -> Self {
        Hit {
            t,
            alpha,
            key,
            slot,
            front: 0.0,
        }
    }
}

#[inline(always)]
pub(crate) fn before(a: (f32, u64), b: (f32, u64)) -> bool {
    a.0 < b.0 || (a.0 == b.0 && a.1 < b.1)
}

/// t's bits made monotonic: the IEEE total order, −0 first made +0 (which [`before`] counts
/// equal to it), so that for t that are not NaN (a hit's never is) the integer order is `<`'s.
#[inline(always)]
fn t_order(t: f32) -> u32 {
    let b = (t + 0.0).to_bits();
    if b >> 31 == 1 {
        !b
    } else {
        b | 0x8000_0000
    }
}

/// The up to [`BATCH`] nearest hits accepted so far, sorted by (t, key), each with the
/// transmittance in front of it. Its `upper` bound only shrinks: a new hit must come before it,
/// and the BVH prunes nodes beyond `upper.0`.
///
/// The transmittances are the sequential product in sorted order, `T_{i+1} = T_i (1 − α_i)` from
/// the carried-in `T_0`: the very product the weights w_i = T_i α_i of eq. surface-record need.
/// Hits do not arrive in order (a wide BVH's traversal is only roughly front to back: measured
/// 19 places out of order per hit on a learned surface), so order is made lazily, in two phases.
/// *Filling*: while the buffer has room and the running product of (1 − α) in arrival order is
/// at least [`T_MIN`], the bound is `t_max` whatever the order, so a hit is appended unsorted
/// (O(1)). When that product falls below [`T_MIN`], the buffer fills, or the batch is read, the
/// buffer is sorted once and its transmittances derived front to back, cutting the ray at the
/// first hit that drops the exact product below [`T_MIN`]. *Sorted*: from then on a hit (which
/// must come before the bound) is shifted into place, evicting the farthest when full; the
/// transmittances from its place on are marked stale, and the running product is kept by
/// multiplying in the new hit's factor and dividing out an evicted one's. The hits at the end
/// that it shows are surely behind the cut ([`CUT_SURELY`]) leave at once, and the bound is the
/// last hit; the exact transmittances (and the exact cut, which may lie a few hits earlier) are
/// derived only when the batch is read, or after [`DRIFT_MAX`] updates. So an insert costs the
/// shift, not a pass over the hits behind it. Pruning by a bound a little beyond the exact cut
/// only lets the traversal take hits the reading then drops: the batch read is the definition's.
/// Invariant: every settled hit but the last leaves at least [`T_MIN`] behind it.
pub(crate) struct HitBatch {
    hits: [Hit; BATCH],
    len: usize,
    /// Still filling: `hits[..len]` in arrival order, nothing settled, the bound `t_max`.
    filling: bool,
    /// `hits[..settled]` have exact transmittances.
    settled: usize,
    /// Transmittance behind all buffered hits: the running product, exact when everything is
    /// settled.
    behind: f32,
    /// The buffer ends at a hit that drops the transmittance below [`T_MIN`]: exactly where
    /// settled, surely (it may end a few hits after the exact cut) where not.
    cut: bool,
    /// Multiplications and divisions of `behind` since it was last derived exactly.
    drift: u32,
    /// Times `drift` reached [`DRIFT_MAX`] (for the tests: that path is exercised).
    #[cfg(test)]
    drift_settles: u32,
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
            filling: true,
            settled: 0,
            behind: carry,
            cut: false,
            drift: 0,
            #[cfg(test)]
            drift_settles: 0,
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
    #[inline(always)]
    pub fn insert(&mut self, hit: Hit) {
        debug_assert!(self.accepts(hit.t, hit.key));
        if self.filling {
            self.hits[self.len] = hit;
            self.len += 1;
            self.behind *= 1.0 - hit.alpha;
            if self.behind < T_MIN || self.len == BATCH {
                self.order();
            }
        } else {
            self.insert_sorted(hit);
        }
    }

    /// [`HitBatch::insert`] once the buffer is sorted.
    #[inline(never)]
    fn insert_sorted(&mut self, hit: Hit) {
        if self.len == BATCH {
            // The farthest hit leaves (the new one comes before it: it was accepted).
            self.len -= 1;
            self.behind /= 1.0 - self.hits[self.len].alpha;
        }
        let mut p = self.len;
        while p > 0 && before((hit.t, hit.key), (self.hits[p - 1].t, self.hits[p - 1].key)) {
            self.hits[p] = self.hits[p - 1];
            p -= 1;
        }
        self.hits[p] = hit;
        self.len += 1;
        self.settled = self.settled.min(p);
        self.behind *= 1.0 - hit.alpha;
        // Hits the product in front of them has surely left below T_MIN leave too.
        let mut removed = 0;
        while self.len > 1 {
            let last = self.hits[self.len - 1].alpha;
            let without = self.behind / (1.0 - last);
            if without >= CUT_SURELY {
                break;
            }
            self.behind = without;
            self.len -= 1;
            removed += 1;
        }
        self.settled = self.settled.min(self.len);
        self.drift += 2 + removed;
        if self.drift > DRIFT_MAX {
            #[cfg(test)]
            {
                self.drift_settles += 1;
            }
            self.settle();
        } else {
            self.cut = self.behind < CUT_SURELY;
        }
        self.rebound();
    }

    /// Ends the filling phase: sorts the buffer by [`before`] (a total order on hits: every key is
    /// distinct, so there is one sorted order), settles it all, and bounds the batch by its last
    /// hit when it is cut or full. The sort is of 64-bit integers, [`t_order`] over the buffer
    /// index, which the standard library sorts with a branchless network (measured against
    /// sorting the hits by a 128-bit (t, key), with the fill inlined: the learned scene's render
    /// +2-3 %, composited camera rays on the 200k room +4 %); runs of equal
    /// t (coplanar surfels) are then put in key order.
    fn order(&mut self) {
        self.filling = false;
        let n = self.len;
        let mut keys = [0u64; BATCH];
        for (i, (k, h)) in keys.iter_mut().zip(&self.hits[..n]).enumerate() {
            *k = (t_order(h.t) as u64) << 32 | i as u64;
        }
        keys[..n].sort_unstable();
        let arrived = self.hits;
        for (h, k) in self.hits[..n].iter_mut().zip(&keys[..n]) {
            *h = arrived[(k & 0xffff_ffff) as usize];
        }
        let mut i = 0;
        while i < n {
            let t = keys[i] >> 32;
            let mut j = i + 1;
            while j < n && keys[j] >> 32 == t {
                j += 1;
            }
            if j - i > 1 {
                self.hits[i..j].sort_unstable_by_key(|h| h.key);
            }
            i = j;
        }
        self.settled = 0;
        self.settle();
        self.rebound();
    }

    /// Bounds the batch by its last hit once it is cut or full: nothing behind that hit can
    /// enter it any more.
    #[inline(always)]
    fn rebound(&mut self) {
        if self.cut || self.len == BATCH {
            let last = self.hits[self.len - 1];
            self.upper = (last.t, last.key);
        }
    }

    /// Re-derives the stale transmittances front to back, and cuts the ray at the first hit that
    /// drops the product below [`T_MIN`]: everything after it is discarded and nothing behind
    /// it is looked for. Without such a hit, any earlier cut was the evicted farthest hit, and
    /// the ray goes on.
    #[inline]
    fn settle(&mut self) {
        let p = self.settled;
        let mut tr = match p {
            0 => self.carry,
            _ => {
                let h = &self.hits[p - 1];
                h.front * (1.0 - h.alpha)
            }
        };
        self.cut = false;
        for i in p..self.len {
            self.hits[i].front = tr;
            tr *= 1.0 - self.hits[i].alpha;
            if tr < T_MIN {
                self.len = i + 1;
                self.cut = true;
                break;
            }
        }
        self.settled = self.len;
        self.behind = tr;
        self.drift = 0;
    }

    /// Settles the batch once the traversal is done: its hits and their weights are exact.
    #[inline]
    pub fn finish(&mut self) {
        if self.filling {
            self.order();
        } else if self.settled < self.len {
            self.settle();
        }
    }

    /// The hits in order with their weights w = T·α (eq. surface-record). Call
    /// [`HitBatch::finish`] first.
    #[inline]
    pub fn weighted(&self) -> impl Iterator<Item = (f32, &Hit)> {
        debug_assert_eq!(self.settled, self.len);
        self.hits[..self.len].iter().map(|h| (h.front * h.alpha, h))
    }

    /// Whether this batch ends the ray: either the transmittance fell below [`T_MIN`] or the
    /// buffer did not fill, so there is nothing more in range. Call [`HitBatch::finish`] first.
    #[inline]
    pub fn finishes(&self) -> bool {
        self.cut || self.len < BATCH
    }

    /// Where the next batch starts (exclusive) and the transmittance it starts behind. Call
    /// [`HitBatch::finish`] first.
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
        Hit::new(t, alpha, key, 0)
    }

    /// `t_order` orders as `before` does on t: signed zeros (equal), negatives, infinities.
    #[test]
    fn t_order_orders_as_before() {
        let ts = [
            f32::NEG_INFINITY,
            -3.5,
            -1e-30,
            -0.0,
            0.0,
            1e-30,
            0.25,
            0.25f32.next_up(),
            7.0,
            f32::MAX,
            f32::INFINITY,
        ];
        for &a in &ts {
            for &b in &ts {
                assert_eq!(t_order(a) < t_order(b), a < b, "{a} vs {b}");
                assert_eq!(t_order(a) == t_order(b), a == b, "{a} vs {b}");
            }
        }
    }

    #[test]
    fn keeps_the_nearest_sorted_and_bounds_by_the_last() {
        let mut b = HitBatch::new(1.0, f32::INFINITY);
        for i in (0..BATCH as u64 + 10).rev() {
            let h = hit(i as f32 * 0.5, i, 0.01);
            if b.accepts(h.t, h.key) {
                b.insert(h);
            }
        }
        b.finish();
        let ts: Vec<f32> = b.weighted().map(|(_, h)| h.t).collect();
        assert_eq!(ts.len(), BATCH);
        assert!(ts.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(b.bound(), (BATCH - 1) as f32 * 0.5);
        assert!(!b.finishes());
        let (after, tr) = b.resume();
        assert_eq!(after, ((BATCH - 1) as f32 * 0.5, BATCH as u64 - 1));
        assert!((tr - 0.99f32.powi(BATCH as i32)).abs() < 1e-6);
    }

    #[test]
    fn cuts_at_negligible_transmittance_and_ties_break_by_key() {
        let mut b = HitBatch::new(1.0, 10.0);
        for key in [5u64, 3, 9, 1, 7] {
            b.insert(hit(2.0, key, 0.95));
        }
        b.finish();
        // 0.05³ = 1.25e-4 is not below T_MIN; 0.05⁴ is.
        let keys: Vec<u64> = b.weighted().map(|(_, h)| h.key).collect();
        assert_eq!(keys, vec![1, 3, 5, 7]);
        assert!(b.finishes());
        assert!(!b.accepts(2.0, 8));
        assert!(b.accepts(2.0, 6));
    }

    /// Against the definition: whatever order hits arrive in (shuffled, nearly sorted as a
    /// traversal yields them, or farthest first: thousands of hits, each evicting or cutting the
    /// last, so the running product is re-derived after DRIFT_MAX updates), the batch holds the sorted nearest hits up to BATCH or up to the
    /// first that drops the transmittance below T_MIN, with the weights of the sequential
    /// product in sorted order, bit for bit; and resumes behind the last of them.
    #[test]
    fn holds_the_sorted_prefix_whatever_the_arrival_order() {
        use crate::scene::synthetic::SplitMix;
        let mut rng = SplitMix(7);
        let (mut cuts, mut drift_settles) = (0, 0);
        for case in 0..400 {
            let reversed = case % 5 == 4;
            let n = if reversed {
                1500 + (rng.range(0.0, 1500.0)) as usize
            } else {
                1 + (rng.range(0.0, 3.0 * BATCH as f32)) as usize
            };
            let faint = case % 2 == 0;
            let mut all: Vec<Hit> = (0..n)
                .map(|i| {
                    let alpha = if faint {
                        rng.range(0.004, 0.1)
                    } else {
                        rng.range(0.004, 0.99)
                    };
                    // Some equal t, so the key decides.
                    let t = (rng.range(0.0, 50.0) as u32) as f32 * 0.1;
                    let t = if reversed { rng.range(0.0, 50.0) } else { t };
                    hit(t, i as u64, alpha)
                })
                .collect();
            let carry = rng.range(0.01, 1.0);
            // Arrival order: shuffled, or sorted with local swaps.
            let mut arrival = all.clone();
            if reversed {
                arrival.sort_by(|a, b| b.t.total_cmp(&a.t).then(b.key.cmp(&a.key)));
            } else if case % 3 == 0 {
                arrival.sort_by(|a, b| a.t.total_cmp(&b.t).then(a.key.cmp(&b.key)));
                for i in 1..n {
                    if rng.range(0.0, 1.0) < 0.3 {
                        arrival.swap(i - 1, i);
                    }
                }
            } else {
                for i in (1..n).rev() {
                    let j = rng.range(0.0, i as f32 + 0.999) as usize;
                    arrival.swap(i, j.min(i));
                }
            }
            let mut b = HitBatch::new(carry, f32::INFINITY);
            for h in &arrival {
                if b.accepts(h.t, h.key) {
                    b.insert(*h);
                }
            }
            drift_settles += b.drift_settles;
            b.finish();
            // The definition.
            all.sort_by(|a, b| a.t.total_cmp(&b.t).then(a.key.cmp(&b.key)));
            let mut want = Vec::new();
            let mut tr = carry;
            let mut cut = false;
            for h in all.iter().take(BATCH) {
                want.push((tr * h.alpha, h.key));
                tr *= 1.0 - h.alpha;
                if tr < T_MIN {
                    cut = true;
                    break;
                }
            }
            cuts += cut as usize;
            let got: Vec<(f32, u64)> = b.weighted().map(|(w, h)| (w, h.key)).collect();
            assert_eq!(got, want, "case {case}");
            assert_eq!(b.finishes(), cut || want.len() < BATCH, "case {case}");
            assert_eq!(b.resume().1, tr, "case {case}");
        }
        assert!(cuts > 50, "cases that reach T_MIN: {cuts}");
        assert!(
            drift_settles > 20,
            "re-derivations after DRIFT_MAX: {drift_settles}"
        );
    }
}
