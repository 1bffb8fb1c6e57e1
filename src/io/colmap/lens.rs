//! COLMAP's camera models (`src/colmap/sensor/models.h` in COLMAP): each model's projection of
//! a camera-frame point to a pixel, its inverse, and the pinhole camera an image of it is
//! resampled into. LightFuse's tracer and splatter are pinhole-only, so a distorted photo is
//! undistorted once on import ([`Lens::pinhole`], [`Lens::source_pixel`]) rather than taught to
//! every kernel.
//!
//! Written by hand because no maintained Rust crate implements COLMAP's models (the
//! `opencv` bindings cover three of them and need a system OpenCV); each model is checked
//! against pycolmap's own `img_from_cam` in `tests/colmap.rs` (fixtures written by
//! `tests/data/colmap/make_fixtures.py`).
//!
//! Conventions are COLMAP's: the camera looks down +Z with +Y down; pixel centres are at +0.5
//! (the same as LightFuse's); `(u, v) = (x / z, y / z)` are normalised coordinates.

/// A COLMAP camera model, by its id in `cameras.bin` and its name in `cameras.txt`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LensModel {
    SimplePinhole,
    Pinhole,
    SimpleRadial,
    Radial,
    OpenCv,
    OpenCvFisheye,
    FullOpenCv,
    Fov,
    SimpleRadialFisheye,
    RadialFisheye,
    ThinPrismFisheye,
    RadTanThinPrismFisheye,
    SimpleDivision,
    Division,
    SimpleFisheye,
    Fisheye,
    Eucm,
    Equirectangular,
}

/// (model, id, name, number of parameters), COLMAP's table.
const MODELS: [(LensModel, i32, &str, usize); 18] = [
    (LensModel::SimplePinhole, 0, "SIMPLE_PINHOLE", 3),
    (LensModel::Pinhole, 1, "PINHOLE", 4),
    (LensModel::SimpleRadial, 2, "SIMPLE_RADIAL", 4),
    (LensModel::Radial, 3, "RADIAL", 5),
    (LensModel::OpenCv, 4, "OPENCV", 8),
    (LensModel::OpenCvFisheye, 5, "OPENCV_FISHEYE", 8),
    (LensModel::FullOpenCv, 6, "FULL_OPENCV", 12),
    (LensModel::Fov, 7, "FOV", 5),
    (
        LensModel::SimpleRadialFisheye,
        8,
        "SIMPLE_RADIAL_FISHEYE",
        4,
    ),
    (LensModel::RadialFisheye, 9, "RADIAL_FISHEYE", 5),
    (LensModel::ThinPrismFisheye, 10, "THIN_PRISM_FISHEYE", 12),
    (
        LensModel::RadTanThinPrismFisheye,
        11,
        "RAD_TAN_THIN_PRISM_FISHEYE",
        16,
    ),
    (LensModel::SimpleDivision, 12, "SIMPLE_DIVISION", 4),
    (LensModel::Division, 13, "DIVISION", 5),
    (LensModel::SimpleFisheye, 14, "SIMPLE_FISHEYE", 3),
    (LensModel::Fisheye, 15, "FISHEYE", 4),
    (LensModel::Eucm, 16, "EUCM", 6),
    (LensModel::Equirectangular, 17, "EQUIRECTANGULAR", 2),
];

impl LensModel {
    pub fn from_id(id: i32) -> Option<LensModel> {
        MODELS.iter().find(|m| m.1 == id).map(|m| m.0)
    }

    pub fn from_name(name: &str) -> Option<LensModel> {
        MODELS.iter().find(|m| m.2 == name).map(|m| m.0)
    }

    fn row(self) -> &'static (LensModel, i32, &'static str, usize) {
        MODELS
            .iter()
            .find(|m| m.0 == self)
            .expect("every model has a row")
    }

    pub fn name(self) -> &'static str {
        self.row().2
    }

    pub fn num_params(self) -> usize {
        self.row().3
    }

    /// True for the models with one focal length `f` (parameters `f, cx, cy, ...`); the others
    /// have `fx, fy, cx, cy, ...`.
    fn one_focal_length(self) -> bool {
        matches!(
            self,
            LensModel::SimplePinhole
                | LensModel::SimpleRadial
                | LensModel::Radial
                | LensModel::SimpleRadialFisheye
                | LensModel::RadialFisheye
                | LensModel::SimpleDivision
                | LensModel::SimpleFisheye
        )
    }

    /// Every model name COLMAP defines, for error messages.
    pub fn names() -> String {
        MODELS.iter().map(|m| m.2).collect::<Vec<_>>().join(", ")
    }
}

/// A camera of the model with its parameters (in COLMAP's order) and image size.
#[derive(Clone, Debug, PartialEq)]
pub struct Lens {
    pub model: LensModel,
    pub width: u32,
    pub height: u32,
    pub params: Vec<f64>,
}

/// The pinhole camera a photo is resampled into: focal lengths and principal point in pixels,
/// the photo's own size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

impl Lens {
    /// True when the model has no distortion: its image is already a pinhole image.
    pub fn is_pinhole(&self) -> bool {
        matches!(self.model, LensModel::SimplePinhole | LensModel::Pinhole)
    }

    /// (fx, fy, cx, cy) of the model's parameters. Every model but EQUIRECTANGULAR has them.
    fn intrinsics(&self) -> (f64, f64, f64, f64) {
        let p = &self.params;
        if self.model.one_focal_length() {
            (p[0], p[0], p[1], p[2])
        } else {
            (p[0], p[1], p[2], p[3])
        }
    }

    /// The distortion parameters: those after the focal length(s) and principal point.
    fn extra(&self) -> &[f64] {
        let k = if self.model.one_focal_length() { 3 } else { 4 };
        &self.params[k.min(self.params.len())..]
    }

    /// Why this model cannot be imported, or None. EQUIRECTANGULAR is a spherical camera: no
    /// pinhole image holds more than a hemisphere of it and LightFuse's cameras are pinholes.
    pub fn unsupported(&self) -> Option<String> {
        (self.model == LensModel::Equirectangular).then(|| {
            "EQUIRECTANGULAR (spherical) cameras are refused: LightFuse's cameras are pinholes; \
             cut the panoramas into perspective views (e.g. COLMAP's `panorama_to_perspective`) \
             and reconstruct those"
                .to_string()
        })
    }

    /// The pixel (COLMAP's `ImgFromCam`) of the camera-frame point `p` (+Z forward), or None
    /// when the model cannot project it (behind a perspective camera; outside the division
    /// model's range).
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        let (fx, fy, cx, cy) = self.intrinsics();
        let e = self.extra();
        let [x, y, z] = p;
        let (u, v) = match self.model {
            LensModel::SimpleFisheye
            | LensModel::Fisheye
            | LensModel::Eucm
            | LensModel::OpenCvFisheye
            | LensModel::SimpleRadialFisheye
            | LensModel::RadialFisheye
            | LensModel::ThinPrismFisheye
            | LensModel::RadTanThinPrismFisheye => return self.project_fisheye(p),
            LensModel::Equirectangular => return None,
            _ => {
                if z <= 0.0 {
                    return None;
                }
                (x / z, y / z)
            }
        };
        let (ud, vd) = match self.model {
            LensModel::SimplePinhole | LensModel::Pinhole => (u, v),
            LensModel::SimpleRadial => {
                let r2 = u * u + v * v;
                let radial = e[0] * r2;
                (u + u * radial, v + v * radial)
            }
            LensModel::Radial => {
                let r2 = u * u + v * v;
                let radial = e[0] * r2 + e[1] * r2 * r2;
                (u + u * radial, v + v * radial)
            }
            LensModel::OpenCv => {
                let (k1, k2, p1, p2) = (e[0], e[1], e[2], e[3]);
                let (u2, v2, uv) = (u * u, v * v, u * v);
                let r2 = u2 + v2;
                let radial = k1 * r2 + k2 * r2 * r2;
                (
                    u + u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u2),
                    v + v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2),
                )
            }
            LensModel::FullOpenCv => {
                let (k1, k2, p1, p2, k3, k4, k5, k6) =
                    (e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7]);
                let (u2, v2, uv) = (u * u, v * v, u * v);
                let r2 = u2 + v2;
                let (r4, r6) = (r2 * r2, r2 * r2 * r2);
                let radial =
                    (1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6);
                (
                    u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u2),
                    v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2),
                )
            }
            LensModel::Fov => {
                // Devernay and Faugeras' field-of-view model, with COLMAP's series where the
                // closed form divides by ~0.
                let omega = e[0];
                let r2 = u * u + v * v;
                let w2 = omega * omega;
                let eps = 1e-4;
                let factor = if w2 < eps {
                    w2 * r2 / 3.0 - w2 / 12.0 + 1.0
                } else if r2 < eps {
                    let t = (omega / 2.0).tan();
                    -2.0 * t * (4.0 * r2 * t * t - 3.0) / (3.0 * omega)
                } else {
                    let r = r2.sqrt();
                    (r * 2.0 * (omega / 2.0).tan()).atan() / (r * omega)
                };
                (u * factor, v * factor)
            }
            LensModel::SimpleDivision | LensModel::Division => {
                // The division model maps distorted to undistorted, u = ud / (1 + k rd^2);
                // projecting solves k ru rd^2 - rd + ru = 0 for the root that is ~ru.
                let k = e[0];
                let ru = (u * u + v * v).sqrt();
                if ru < 1e-12 || k.abs() < 1e-15 {
                    (u, v)
                } else {
                    let disc = 1.0 - 4.0 * k * ru * ru;
                    if disc < 0.0 {
                        return None;
                    }
                    let rd = 2.0 * ru / (1.0 + disc.sqrt());
                    (u * rd / ru, v * rd / ru)
                }
            }
            _ => unreachable!("fisheye models return above"),
        };
        Some([fx * ud + cx, fy * vd + cy])
    }

    /// The fisheye models, which are defined on the ray's angle θ from the axis (so also for
    /// points beside or behind the camera).
    fn project_fisheye(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        let (fx, fy, cx, cy) = self.intrinsics();
        let e = self.extra();
        let [x, y, z] = p;
        let rxy = (x * x + y * y).sqrt();
        let theta = rxy.atan2(z);
        // The unit direction in the image plane, (x, y) / |(x, y)|, times θ: COLMAP's
        // equidistant `(uu, vv)`.
        let (uu, vv) = if rxy > f64::EPSILON {
            (theta * x / rxy, theta * y / rxy)
        } else {
            (0.0, 0.0)
        };
        let (ud, vd) = match self.model {
            LensModel::SimpleFisheye | LensModel::Fisheye => (uu, vv),
            LensModel::Eucm => {
                let (alpha, beta) = (e[0], e[1]);
                let d = (beta * (x * x + y * y) + z * z).sqrt();
                let denom = alpha * d + (1.0 - alpha) * z;
                if denom <= 0.0 {
                    return None;
                }
                (x / denom, y / denom)
            }
            LensModel::OpenCvFisheye
            | LensModel::SimpleRadialFisheye
            | LensModel::RadialFisheye => {
                let t2 = theta * theta;
                let k: &[f64] = match self.model {
                    LensModel::SimpleRadialFisheye => &e[..1],
                    LensModel::RadialFisheye => &e[..2],
                    _ => &e[..4],
                };
                // θ_d = θ (1 + k1 θ² + k2 θ⁴ + ...).
                let mut poly = 1.0;
                let mut tp = t2;
                for &ki in k {
                    poly += ki * tp;
                    tp *= t2;
                }
                (uu * poly, vv * poly)
            }
            LensModel::ThinPrismFisheye => {
                let (k1, k2, p1, p2, k3, k4, sx1, sy1) =
                    (e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7]);
                let t2 = uu * uu + vv * vv;
                let (t4, t6, t8) = (t2 * t2, t2 * t2 * t2, t2 * t2 * t2 * t2);
                let radial = k1 * t2 + k2 * t4 + k3 * t6 + k4 * t8;
                let uv = uu * vv;
                (
                    uu + uu * radial + 2.0 * p1 * uv + p2 * (t2 + 2.0 * uu * uu) + sx1 * t2,
                    vv + vv * radial + 2.0 * p2 * uv + p1 * (t2 + 2.0 * vv * vv) + sy1 * t2,
                )
            }
            LensModel::RadTanThinPrismFisheye => {
                // Project Aria's FisheyeRadTanThinPrism: radial on θ, then tangential and
                // thin-prism terms on the radially distorted point.
                let k = &e[..6];
                let (p0, p1) = (e[6], e[7]);
                let s = &e[8..12];
                let t2 = theta * theta;
                let mut poly = 1.0;
                let mut tp = t2;
                for &ki in k {
                    poly += ki * tp;
                    tp *= t2;
                }
                let (xr, yr) = (uu * poly, vv * poly);
                let r2 = xr * xr + yr * yr;
                let r4 = r2 * r2;
                let temp = 2.0 * (xr * p0 + yr * p1);
                (
                    xr + temp * xr + r2 * p0 + s[0] * r2 + s[1] * r4,
                    yr + temp * yr + r2 * p1 + s[2] * r2 + s[3] * r4,
                )
            }
            _ => unreachable!("perspective models are handled by project"),
        };
        Some([fx * ud + cx, fy * vd + cy])
    }

    /// The camera-frame ray `(u, v, 1)` (a direction; +Z forward) whose projection is the pixel
    /// `px`, found by Newton's method on [`Lens::project`] with a finite-difference Jacobian
    /// (the models' own inverses are iterative in COLMAP too), or None when it does not
    /// converge. Only for rays in front of the camera (θ < 90°), which is all a pinhole image
    /// can hold.
    pub fn unproject(&self, px: [f64; 2]) -> Option<[f64; 2]> {
        let (fx, fy, cx, cy) = self.intrinsics();
        let mut q = [(px[0] - cx) / fx, (px[1] - cy) / fy];
        let f = |q: [f64; 2]| self.project([q[0], q[1], 1.0]);
        for _ in 0..100 {
            let r = f(q)?;
            let res = [r[0] - px[0], r[1] - px[1]];
            if res[0].abs() < 1e-9 && res[1].abs() < 1e-9 {
                return Some(q);
            }
            let h = 1e-7 * (1.0 + q[0].abs().max(q[1].abs()));
            let ru = f([q[0] + h, q[1]])?;
            let rv = f([q[0], q[1] + h])?;
            let j = [
                [(ru[0] - r[0]) / h, (rv[0] - r[0]) / h],
                [(ru[1] - r[1]) / h, (rv[1] - r[1]) / h],
            ];
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            if det.abs() < 1e-300 {
                return None;
            }
            let du = (j[1][1] * res[0] - j[0][1] * res[1]) / det;
            let dv = (-j[1][0] * res[0] + j[0][0] * res[1]) / det;
            // Halve steps that would not reduce the residual (strong fisheye distortion).
            let mut step = 1.0;
            let norm = res[0].hypot(res[1]);
            loop {
                let cand = [q[0] - step * du, q[1] - step * dv];
                if let Some(rc) = f(cand) {
                    if (rc[0] - px[0]).hypot(rc[1] - px[1]) < norm || step < 1e-6 {
                        q = cand;
                        break;
                    }
                }
                step *= 0.5;
                if step < 1e-6 {
                    return None;
                }
            }
        }
        None
    }

    /// The pinhole camera this photo is resampled into: the model's own focal lengths scaled
    /// by the least factor for which every pixel of the pinhole image sees a ray the photo
    /// recorded (< 1 for barrel distortion, which records a wider field than its focal length
    /// says; > 1 for pincushion and fisheye), the principal point and the photo's size kept.
    /// This is COLMAP's `image_undistorter` with `blank_pixels = 0`, except that COLMAP keeps
    /// the focal length and changes the image size, while we keep the size (what every later
    /// stage is budgeted for) and change the focal length. A pinhole model is returned as it
    /// is. None when the border cannot be undistorted (a distortion that folds over).
    pub fn pinhole(&self) -> Option<Pinhole> {
        let (fx, fy, cx, cy) = self.intrinsics();
        let (w, h) = (self.width as f64, self.height as f64);
        let mut zoom: f64 = 1.0;
        if !self.is_pinhole() {
            zoom = 0.0;
            // The photo's border, undistorted: the pinhole image must stay inside it. Each side
            // limits the half-extent on its side of the principal point.
            let n = 64;
            for i in 0..=n {
                let t = i as f64 / n as f64;
                for (px, side) in [
                    ([0.0, t * h], 0),
                    ([w, t * h], 1),
                    ([t * w, 0.0], 2),
                    ([t * w, h], 3),
                ] {
                    let q = self.unproject(px)?;
                    // Pixel extent of the kept image on this side, in normalised units at
                    // zoom 1, over what the border reaches.
                    let need = match side {
                        0 => cx / fx / (-q[0]).max(1e-9),
                        1 => (w - cx) / fx / q[0].max(1e-9),
                        2 => cy / fy / (-q[1]).max(1e-9),
                        _ => (h - cy) / fy / q[1].max(1e-9),
                    };
                    zoom = zoom.max(need);
                }
            }
        }
        Some(Pinhole {
            fx: fx * zoom,
            fy: fy * zoom,
            cx,
            cy,
            width: self.width,
            height: self.height,
        })
    }

    /// Where in the photo (pixel coordinates, centres at +0.5) the pinhole image's pixel
    /// position `px` comes from.
    pub fn source_pixel(&self, pin: &Pinhole, px: [f64; 2]) -> Option<[f64; 2]> {
        let u = (px[0] - pin.cx) / pin.fx;
        let v = (px[1] - pin.cy) / pin.fy;
        self.project([u, v, 1.0])
    }
}
