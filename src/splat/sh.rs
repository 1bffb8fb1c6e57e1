//! View-dependent colour from spherical harmonics, exactly as 3DGS evaluates it (and as
//! `docs/formats.md` stores it: KHR order, degree then coefficient, with a 0.5 DC bias):
//! `c = max(Σ_k f_k Y_k(d) + 0.5, 0)` per channel, `d` the unit vector from the camera centre to
//! the surfel centre. The rasteriser evaluates it once per surfel in f32 (`*_f32`), the reference
//! in f64; both are generated from the same source below.

/// Real SH normalisation constants in 3DGS's basis and sign convention.
const K0: f64 = 0.282_094_791_773_878_14;
const K1: f64 = 0.488_602_511_902_919_9;
const K2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const K3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// The DC bias the files carry (formats.md: "0.5 DC bias").
pub const DC_BIAS: f64 = 0.5;

macro_rules! sh_functions {
    (
        $t:ty,
        $basis:ident,
        $view_dir:ident,
        $eval:ident,
        $backward:ident,
        $color_backward:ident,
        $backward_basis:ident
    ) => {
        /// Basis values `Y_k(d)` for the `n ≤ 16` coefficients of a degree, and, if asked for, their
        /// gradients with respect to `d` (as a polynomial in x, y, z; the caller projects out the radial
        /// part).
        pub fn $basis(d: [$t; 3], n: usize, y: &mut [$t; 16], dy: Option<&mut [[$t; 3]; 16]>) {
            const C0: $t = K0 as $t;
            const C1: $t = K1 as $t;
            const C2: [$t; 5] = [
                K2[0] as $t,
                K2[1] as $t,
                K2[2] as $t,
                K2[3] as $t,
                K2[4] as $t,
            ];
            const C3: [$t; 7] = [
                K3[0] as $t,
                K3[1] as $t,
                K3[2] as $t,
                K3[3] as $t,
                K3[4] as $t,
                K3[5] as $t,
                K3[6] as $t,
            ];
            let [x, yv, z] = d;
            let (xx, yy, zz) = (x * x, yv * yv, z * z);
            y[0] = C0;
            if n > 1 {
                y[1] = -C1 * yv;
                y[2] = C1 * z;
                y[3] = -C1 * x;
            }
            if n > 4 {
                y[4] = C2[0] * x * yv;
                y[5] = C2[1] * yv * z;
                y[6] = C2[2] * (2.0 * zz - xx - yy);
                y[7] = C2[3] * x * z;
                y[8] = C2[4] * (xx - yy);
            }
            if n > 9 {
                y[9] = C3[0] * yv * (3.0 * xx - yy);
                y[10] = C3[1] * x * yv * z;
                y[11] = C3[2] * yv * (4.0 * zz - xx - yy);
                y[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
                y[13] = C3[4] * x * (4.0 * zz - xx - yy);
                y[14] = C3[5] * z * (xx - yy);
                y[15] = C3[6] * x * (xx - 3.0 * yy);
            }
            let Some(dy) = dy else { return };
            dy[0] = [0.0; 3];
            if n > 1 {
                dy[1] = [0.0, -C1, 0.0];
                dy[2] = [0.0, 0.0, C1];
                dy[3] = [-C1, 0.0, 0.0];
            }
            if n > 4 {
                dy[4] = [C2[0] * yv, C2[0] * x, 0.0];
                dy[5] = [0.0, C2[1] * z, C2[1] * yv];
                dy[6] = [-2.0 * C2[2] * x, -2.0 * C2[2] * yv, 4.0 * C2[2] * z];
                dy[7] = [C2[3] * z, 0.0, C2[3] * x];
                dy[8] = [2.0 * C2[4] * x, -2.0 * C2[4] * yv, 0.0];
            }
            if n > 9 {
                dy[9] = [C3[0] * 6.0 * x * yv, C3[0] * 3.0 * (xx - yy), 0.0];
                dy[10] = [C3[1] * yv * z, C3[1] * x * z, C3[1] * x * yv];
                dy[11] = [
                    -2.0 * C3[2] * x * yv,
                    C3[2] * (4.0 * zz - xx - 3.0 * yy),
                    8.0 * C3[2] * yv * z,
                ];
                dy[12] = [
                    -6.0 * C3[3] * x * z,
                    -6.0 * C3[3] * yv * z,
                    C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy),
                ];
                dy[13] = [
                    C3[4] * (4.0 * zz - 3.0 * xx - yy),
                    -2.0 * C3[4] * x * yv,
                    8.0 * C3[4] * x * z,
                ];
                dy[14] = [
                    2.0 * C3[5] * x * z,
                    -2.0 * C3[5] * yv * z,
                    C3[5] * (xx - yy),
                ];
                dy[15] = [C3[6] * 3.0 * (xx - yy), -6.0 * C3[6] * x * yv, 0.0];
            }
        }

        /// Unit view direction from the camera centre `o` to the surfel centre `p`, and |p − o|.
        pub fn $view_dir(o: [$t; 3], p: [$t; 3]) -> ([$t; 3], $t) {
            let a = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
            let len = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
            if len > 0.0 {
                ([a[0] / len, a[1] / len, a[2] / len], len)
            } else {
                ([0.0, 0.0, 1.0], 0.0)
            }
        }

        /// Colour before the clamp, `Σ_k f_k Y_k(d) + 0.5`, for SH triples `f` (any degree ≤ 3).
        pub fn $eval(d: [$t; 3], f: &[[$t; 3]]) -> [$t; 3] {
            let mut y = [0.0; 16];
            $basis(d, f.len(), &mut y, None);
            let mut c = [DC_BIAS as $t; 3];
            for (fk, yk) in f.iter().zip(&y) {
                for ch in 0..3 {
                    c[ch] += fk[ch] * yk;
                }
            }
            c
        }

        /// Backward of `eval` followed by the clamp at 0: given the unclamped colour `raw` and dL/dc,
        /// writes dL/df_k into `d_f` and returns dL/d(p − o) through the view direction (`len` = |p − o|).
        pub fn $backward(
            d: [$t; 3],
            len: $t,
            f: &[[$t; 3]],
            raw: [$t; 3],
            d_color: [$t; 3],
            d_f: &mut [[f32; 3]],
        ) -> [$t; 3] {
            let mut y = [0.0; 16];
            let mut dy = [[0.0; 3]; 16];
            $basis(d, f.len(), &mut y, Some(&mut dy));
            $backward_basis(d, len, f, raw, d_color, d_f, &y, &dy)
        }

        /// [`eval`] and its backward at once (the basis is evaluated once): returns the unclamped
        /// colour, bit for bit as `eval` computes it, and dL/d(p − o) as the backward does.
        pub fn $color_backward(
            d: [$t; 3],
            len: $t,
            f: &[[$t; 3]],
            d_color: [$t; 3],
            d_f: &mut [[f32; 3]],
        ) -> ([$t; 3], [$t; 3]) {
            let mut y = [0.0; 16];
            let mut dy = [[0.0; 3]; 16];
            $basis(d, f.len(), &mut y, Some(&mut dy));
            // The same sum, in the same order, as `eval`.
            let mut raw = [DC_BIAS as $t; 3];
            for (fk, yk) in f.iter().zip(&y) {
                for ch in 0..3 {
                    raw[ch] += fk[ch] * yk;
                }
            }
            let g_a = $backward_basis(d, len, f, raw, d_color, d_f, &y, &dy);
            (raw, g_a)
        }

        #[allow(clippy::too_many_arguments)]
        fn $backward_basis(
            d: [$t; 3],
            len: $t,
            f: &[[$t; 3]],
            raw: [$t; 3],
            d_color: [$t; 3],
            d_f: &mut [[f32; 3]],
            y: &[$t; 16],
            dy: &[[$t; 3]; 16],
        ) -> [$t; 3] {
            // 3DGS: a clamped channel passes no gradient.
            let g = [0, 1, 2].map(|ch| if raw[ch] < 0.0 { 0.0 } else { d_color[ch] });
            let mut g_dir = [0.0; 3];
            for k in 0..f.len() {
                d_f[k] = [
                    (g[0] * y[k]) as f32,
                    (g[1] * y[k]) as f32,
                    (g[2] * y[k]) as f32,
                ];
                let gf = g[0] * f[k][0] + g[1] * f[k][1] + g[2] * f[k][2];
                for j in 0..3 {
                    g_dir[j] += gf * dy[k][j];
                }
            }
            if len == 0.0 {
                return [0.0; 3];
            }
            // d = a / |a|: dd/da = (I − d dᵀ) / |a|.
            let radial = g_dir[0] * d[0] + g_dir[1] * d[1] + g_dir[2] * d[2];
            [0, 1, 2].map(|j| (g_dir[j] - radial * d[j]) / len)
        }
    };
}

sh_functions!(
    f64,
    basis,
    view_dir,
    eval,
    backward,
    color_backward,
    backward_basis
);
sh_functions!(
    f32,
    basis_f32,
    view_dir_f32,
    eval_f32,
    backward_f32,
    color_backward_f32,
    backward_basis_f32
);

#[cfg(test)]
mod tests {
    use super::*;

    /// Points on the unit sphere, a Fibonacci lattice: nearly equal areas 4π / n.
    fn fibonacci(n: usize) -> Vec<[f64; 3]> {
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        (0..n)
            .map(|i| {
                let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
                let r = (1.0 - z * z).sqrt();
                let phi = golden * i as f64;
                [r * phi.cos(), r * phi.sin(), z]
            })
            .collect()
    }

    /// A wrong constant or a copy-paste slip in a polynomial breaks orthonormality by far more
    /// than the lattice's quadrature error (~1e-5 at 40k points for degree ≤ 6 products).
    #[test]
    fn basis_is_orthonormal() {
        let pts = fibonacci(40_000);
        let mut gram = [[0.0f64; 16]; 16];
        let mut y = [0.0; 16];
        for p in &pts {
            basis(*p, 16, &mut y, None);
            for i in 0..16 {
                for j in 0..16 {
                    gram[i][j] += y[i] * y[j];
                }
            }
        }
        let w = 4.0 * std::f64::consts::PI / pts.len() as f64;
        for (i, row) in gram.iter().enumerate() {
            for (j, g) in row.iter().enumerate() {
                let expect = if i == j { 1.0 } else { 0.0 };
                assert!((g * w - expect).abs() < 1e-3, "<Y{i}, Y{j}> = {}", g * w);
            }
        }
    }

    /// The 3DGS sign convention of degree 1 (Y1 = −C1 y, Y2 = C1 z, Y3 = −C1 x) and that the
    /// hand-written gradients match central differences of the polynomials.
    #[test]
    fn basis_signs_and_gradients() {
        let d = [0.3, -0.5, 0.81];
        let mut y = [0.0; 16];
        let mut dy = [[0.0; 3]; 16];
        basis(d, 16, &mut y, Some(&mut dy));
        assert!((y[1] + K1 * d[1]).abs() < 1e-15);
        assert!((y[2] - K1 * d[2]).abs() < 1e-15);
        assert!((y[3] + K1 * d[0]).abs() < 1e-15);
        let h = 1e-6;
        for j in 0..3 {
            let (mut a, mut b) = (d, d);
            a[j] += h;
            b[j] -= h;
            let (mut ya, mut yb) = ([0.0; 16], [0.0; 16]);
            basis(a, 16, &mut ya, None);
            basis(b, 16, &mut yb, None);
            for k in 0..16 {
                let fd = (ya[k] - yb[k]) / (2.0 * h);
                assert!(
                    (fd - dy[k][j]).abs() < 1e-8,
                    "dY{k}/dx{j}: {fd} vs {}",
                    dy[k][j]
                );
            }
        }
    }

    /// The f32 functions the rasteriser uses agree with the f64 ones to f32 rounding (they are
    /// generated from the same source; this catches a slip in the generation).
    #[test]
    fn f32_matches_f64() {
        let mut f64s = [[0.0f64; 3]; 16];
        for (k, c) in f64s.iter_mut().enumerate() {
            let x = k as f64;
            *c = [(0.7 * x).sin(), (1.3 * x + 0.2).cos() * 0.5, 0.3 - 0.05 * x];
        }
        let f32s: Vec<[f32; 3]> = f64s.iter().map(|c| c.map(|x| x as f32)).collect();
        let f64s: Vec<[f64; 3]> = f32s.iter().map(|c| c.map(f64::from)).collect();
        for (o, p) in [
            ([0.1f32, 0.2, 0.3], [1.5f32, -0.7, 2.2]),
            ([0.0, 0.0, 0.0], [-0.3, 0.9, -0.1]),
            ([2.0, 1.0, -1.0], [2.0, 1.0, -1.0]),
        ] {
            let (d32, l32) = view_dir_f32(o, p);
            let (d64, l64) = view_dir(o.map(f64::from), p.map(f64::from));
            assert!((l32 as f64 - l64).abs() <= 1e-6 * l64.max(1.0));
            for n in [1, 4, 9, 16] {
                let c32 = eval_f32(d32, &f32s[..n]);
                let c64 = eval(d64, &f64s[..n]);
                for ch in 0..3 {
                    assert!(
                        (c32[ch] as f64 - c64[ch]).abs() < 1e-5,
                        "n {n}: {c32:?} {c64:?}"
                    );
                }
                let g = [0.3, -1.2, 0.8];
                let (mut df32, mut df64) = ([[0.0f32; 3]; 16], [[0.0f32; 3]; 16]);
                let a32 = backward_f32(d32, l32, &f32s[..n], c32, g.map(|x| x as f32), &mut df32);
                let a64 = backward(d64, l64, &f64s[..n], c64, g, &mut df64);
                let mut df_fused = [[0.0f32; 3]; 16];
                let (raw, a_fused) =
                    color_backward_f32(d32, l32, &f32s[..n], g.map(|x| x as f32), &mut df_fused);
                assert_eq!((raw, a_fused), (c32, a32));
                assert_eq!(df_fused, df32);
                for j in 0..3 {
                    assert!(
                        (a32[j] as f64 - a64[j]).abs() < 1e-5,
                        "n {n}: {a32:?} {a64:?}"
                    );
                }
                for k in 0..n {
                    for ch in 0..3 {
                        assert!((df32[k][ch] - df64[k][ch]).abs() < 1e-6, "n {n}, k {k}");
                    }
                }
            }
        }
    }
}
