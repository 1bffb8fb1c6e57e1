//! Front-to-back compositing (eq. surface-record), `w_j = α_j Π_{k<j} (1 − α_k)`, one hit at a
//! time, and its adjoint walked back to front.

/// The forward recurrence: the transmittance in front of the next hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Front {
    pub trans: f32,
}

impl Default for Front {
    fn default() -> Self {
        Front { trans: 1.0 }
    }
}

impl Front {
    /// Takes a hit of opacity `alpha`: returns its weight `w = T α` and moves T behind it.
    #[inline(always)]
    pub fn step(&mut self, alpha: f32) -> f32 {
        let w = self.trans * alpha;
        self.trans *= 1.0 - alpha;
        w
    }
}

/// The adjoint, walked from the last composited hit to the first. With `f_j` the values a hit
/// contributes and `gdot_j = ⟨g, f_j⟩` their upstream gradient, the composite behind hit j (as
/// seen from it) is `B_j = α_j gdot_j + (1 − α_j) B_{j+1}` and
/// `dL/dα_j = T_j (gdot_j − B_{j+1})`, where `T_j = T_{j+1} / (1 − α_j)` is recovered by
/// division (α ≤ MAX_OPACITY keeps it stable).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Back {
    /// Transmittance behind the hit about to be stepped (start: behind the last hit).
    pub trans: f32,
    /// Composite of the upstream gradient behind it (start: 0).
    pub behind: f32,
}

impl Back {
    /// Starts behind the last hit, whose transmittance is `trans`.
    #[inline(always)]
    pub fn new(trans: f32) -> Self {
        Back { trans, behind: 0.0 }
    }

    /// Steps over one hit (back to front): returns its weight `w` and `dL/dα`.
    #[inline(always)]
    pub fn step(&mut self, alpha: f32, gdot: f32) -> (f32, f32) {
        let t_in = self.trans / (1.0 - alpha);
        self.trans = t_in;
        let d_alpha = t_in * (gdot - self.behind);
        self.behind = alpha * gdot + (1.0 - alpha) * self.behind;
        (t_in * alpha, d_alpha)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The adjoint against central differences of L = Σ w_j f_j on a short list.
    #[test]
    fn back_is_the_adjoint_of_front() {
        let alphas = [0.3f32, 0.9, 0.5, 0.2];
        let f = [1.0f32, -2.0, 0.5, 3.0];
        let loss = |a: &[f32]| {
            let mut fr = Front::default();
            let l: f64 = a
                .iter()
                .zip(&f)
                .map(|(&x, &y)| (fr.step(x) * y) as f64)
                .sum();
            (l, fr.trans)
        };
        let (_, t_end) = loss(&alphas);
        let mut back = Back::new(t_end);
        for j in (0..alphas.len()).rev() {
            let (w, d_alpha) = back.step(alphas[j], f[j]);
            let mut ap = alphas;
            let mut am = alphas;
            ap[j] += 1e-3;
            am[j] -= 1e-3;
            let fd = (loss(&ap).0 - loss(&am).0) / 2e-3;
            assert!(
                (d_alpha as f64 - fd).abs() < 1e-3,
                "hit {j}: {d_alpha} vs {fd}"
            );
            let mut fr = Front::default();
            let w_fwd = alphas[..=j]
                .iter()
                .map(|&a| fr.step(a))
                .last()
                .unwrap_or(0.0);
            assert!((w - w_fwd).abs() < 1e-6);
        }
        assert!((back.trans - 1.0).abs() < 1e-5);
    }
}
