//! Replayable quasi-random numbers: an Owen-scrambled, shuffled Sobol sequence (Burley 2020,
//! "Practical Hash-based Owen Scrambling", JCGT 9(4)), one independent scramble per pixel.
//!
//! The paper replays "the same Sobol samples during backpropagation" (path replay, §
//! Differentiable one-bounce path tracing), so a sample must be a pure function of
//! (pixel, seed, sample index, dimension): no state, no order dependence. The `sobol_burley`
//! crate (cessen; MIT/Apache-2.0, no dependencies) is exactly that: Joe–Kuo direction numbers
//! for 256 dimensions, a Laine–Karras-style nested uniform scramble with an improved hash, and a
//! hash-shuffled sample index. We only wrap it: the per-pixel seed, the bounds, and more than
//! 256 dimensions by re-seeding.

/// Sample indices `sobol_burley` supports (its direction numbers have 16 bits).
pub const MAX_SAMPLES: u32 = 1 << 16;
/// Dimensions of one Sobol sequence; past this we start a fresh, independently scrambled one.
const DIMS_PER_SEQUENCE: u32 = sobol_burley::NUM_DIMENSIONS;

/// A 32-bit integer hash with full avalanche (Wellons' "lowbias32", hash-prospector).
fn mix32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// The sample stream of one pixel for one run seed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sampler {
    seed: u32,
}

impl Sampler {
    /// The stream of pixel `pixel_index` (any unique id of the pixel in the image or batch)
    /// under the run's `seed`. Different pixels get statistically independent scrambles and
    /// shuffles, so their errors decorrelate (white-noise across pixels).
    pub fn new(pixel_index: u32, seed: u32) -> Sampler {
        Sampler {
            seed: mix32(pixel_index ^ mix32(seed.wrapping_add(0x9e37_79b9))),
        }
    }

    /// Component `dim` of sample `sample_index`, in [0, 1). The first 2^k samples of any one
    /// dimension are stratified into the 2^k intervals of width 2^-k, and so are pairs of
    /// dimensions (0, 1) within a sequence, like every Sobol (0, 2)-sequence.
    ///
    /// # Panics
    /// If `sample_index >= MAX_SAMPLES` (a programming error: spp is bounded by the caller).
    pub fn get(&self, sample_index: u32, dim: u32) -> f32 {
        assert!(
            sample_index < MAX_SAMPLES,
            "Sobol sample index {sample_index} >= {MAX_SAMPLES}"
        );
        let sequence = dim / DIMS_PER_SEQUENCE;
        let seed = if sequence == 0 {
            self.seed
        } else {
            mix32(self.seed ^ mix32(sequence))
        };
        sobol_burley::sample(sample_index, dim % DIMS_PER_SEQUENCE, seed)
    }

    /// Dimensions `dim` and `dim + 1` of sample `sample_index`.
    pub fn get_2d(&self, sample_index: u32, dim: u32) -> [f32; 2] {
        [self.get(sample_index, dim), self.get(sample_index, dim + 1)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_in_unit_interval_past_the_dimension_limit() {
        let s = Sampler::new(3, 4);
        for d in [0, 1, 255, 256, 257, 1000] {
            for i in 0..64 {
                let v = s.get(i, d);
                assert!((0.0..1.0).contains(&v), "{v}");
            }
        }
        assert_ne!(
            s.get(5, 1),
            s.get(5, 257),
            "sequences past 256 are rescrambled"
        );
    }

    #[test]
    #[should_panic(expected = "Sobol sample index")]
    fn too_many_samples_is_refused() {
        Sampler::new(0, 0).get(MAX_SAMPLES, 0);
    }
}
