//! Rigid transforms: how a state or a layout places an object relative to the reference state
//! (docs/design.md §2, "object frame").

use glam::{Mat3, Mat4, Quat, Vec3};

/// A rotation followed by a translation, x ↦ R x + t. Stored as the glTF node stores it, so
/// files round-trip bit for bit.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Rigid {
    /// Unit quaternion (x, y, z, w).
    pub rotation: [f32; 4],
    /// Translation, metres.
    pub translation: [f32; 3],
}

impl Default for Rigid {
    fn default() -> Self {
        Self::IDENTITY
    }
}

/// Tolerance on RᵀR − I and det R − 1 when a 4x4 matrix is accepted as rigid. Matrices written
/// as decimal text by Blender carry ~1e-7 relative error; a real scale or shear is far larger.
pub const RIGID_TOLERANCE: f32 = 1e-4;

impl Rigid {
    pub const IDENTITY: Rigid = Rigid {
        rotation: [0.0, 0.0, 0.0, 1.0],
        translation: [0.0; 3],
    };

    pub fn is_identity(&self) -> bool {
        *self == Self::IDENTITY
    }

    pub fn quat(&self) -> Quat {
        Quat::from_array(self.rotation)
    }

    pub fn matrix(&self) -> Mat4 {
        Mat4::from_rotation_translation(self.quat().normalize(), Vec3::from_array(self.translation))
    }

    /// Rows of the 4x4 matrix, as layout.json and dataset.json store it.
    pub fn rows(&self) -> [[f32; 4]; 4] {
        let m = self.matrix().transpose();
        [
            m.x_axis.to_array(),
            m.y_axis.to_array(),
            m.z_axis.to_array(),
            m.w_axis.to_array(),
        ]
    }

    /// Accepts a 4x4 (rows) that is a rotation plus translation; otherwise says what is wrong.
    pub fn from_rows(rows: &[[f32; 4]; 4]) -> Result<Rigid, String> {
        if rows.iter().flatten().any(|x| !x.is_finite()) {
            return Err("expected finite numbers".into());
        }
        let last = rows[3];
        if last != [0.0, 0.0, 0.0, 1.0] {
            return Err(format!("expected last row [0, 0, 0, 1], found {last:?}"));
        }
        let r = Mat3::from_cols(
            Vec3::new(rows[0][0], rows[1][0], rows[2][0]),
            Vec3::new(rows[0][1], rows[1][1], rows[2][1]),
            Vec3::new(rows[0][2], rows[1][2], rows[2][2]),
        );
        let scales = [r.x_axis.length(), r.y_axis.length(), r.z_axis.length()];
        if scales.iter().any(|s| (s - 1.0).abs() > RIGID_TOLERANCE) {
            return Err(format!(
                "expected a rigid transform (rotation and translation), found scale ({:.6}, {:.6}, {:.6})",
                scales[0], scales[1], scales[2]
            ));
        }
        let shear = (r.transpose() * r - Mat3::IDENTITY).to_cols_array();
        if shear.iter().any(|x| x.abs() > RIGID_TOLERANCE) {
            return Err(
                "expected a rigid transform, found shear (the axes are not orthogonal)".into(),
            );
        }
        if r.determinant() < 0.0 {
            return Err("expected a rotation, found a reflection (negative determinant)".into());
        }
        Ok(Rigid {
            rotation: Quat::from_mat3(&r).normalize().to_array(),
            translation: [rows[0][3], rows[1][3], rows[2][3]],
        })
    }

    /// Composition `self ∘ other`: apply `other`, then `self`.
    pub fn compose(&self, other: &Rigid) -> Rigid {
        let q = self.quat() * other.quat();
        let t =
            self.quat() * Vec3::from_array(other.translation) + Vec3::from_array(self.translation);
        Rigid {
            rotation: q.normalize().to_array(),
            translation: t.to_array(),
        }
    }

    /// The inverse transform, x ↦ Rᵀ (x − t).
    pub fn inverse(&self) -> Rigid {
        let qi = self.quat().normalize().inverse();
        Rigid {
            rotation: qi.to_array(),
            translation: (-(qi * Vec3::from_array(self.translation))).to_array(),
        }
    }

    pub fn transform_point(&self, p: [f32; 3]) -> [f32; 3] {
        (self.quat() * Vec3::from_array(p) + Vec3::from_array(self.translation)).to_array()
    }

    /// Rotates a surfel's orientation: q ↦ q_T q (eq. state-assembly acts on centres and
    /// orientations only).
    pub fn transform_rotation(&self, q: [f32; 4]) -> [f32; 4] {
        (self.quat() * Quat::from_array(q)).to_array()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_round_trip_and_rejects_scale_and_shear() {
        let t = Rigid {
            rotation: Quat::from_rotation_y(0.7).to_array(),
            translation: [1.0, 2.0, -3.0],
        };
        let back = Rigid::from_rows(&t.rows()).unwrap();
        assert!(back.quat().angle_between(t.quat()) < 1e-5);
        assert_eq!(back.translation, t.translation);

        let mut scaled = t.rows();
        for row in scaled.iter_mut().take(3) {
            row[0] *= 1.1;
        }
        assert!(Rigid::from_rows(&scaled).unwrap_err().contains("scale"));

        let mut sheared = Rigid::IDENTITY.rows();
        sheared[0][1] = 0.3;
        let s = 1.0 / (1.0f32 + 0.09).sqrt();
        sheared[0][1] *= s;
        sheared[1][1] *= s;
        assert!(Rigid::from_rows(&sheared).unwrap_err().contains("shear"));

        let mut mirrored = Rigid::IDENTITY.rows();
        mirrored[0][0] = -1.0;
        assert!(Rigid::from_rows(&mirrored)
            .unwrap_err()
            .contains("reflection"));
    }

    #[test]
    fn compose_matches_matrices() {
        let a = Rigid {
            rotation: Quat::from_rotation_x(0.3).to_array(),
            translation: [0.5, 0.0, 1.0],
        };
        let b = Rigid {
            rotation: Quat::from_rotation_z(-1.1).to_array(),
            translation: [0.0, 2.0, 0.0],
        };
        let m = a.matrix() * b.matrix();
        let c = a.compose(&b).matrix();
        assert!(m.abs_diff_eq(c, 1e-5));
    }

    #[test]
    fn inverse_undoes_the_transform() {
        let t = Rigid {
            rotation: Quat::from_axis_angle(Vec3::new(1.0, 2.0, -0.5).normalize(), 0.9).to_array(),
            translation: [0.3, -1.2, 2.5],
        };
        let p = [0.7, 0.1, -0.4];
        let back = t.inverse().transform_point(t.transform_point(p));
        for k in 0..3 {
            assert!((back[k] - p[k]).abs() < 1e-5, "{back:?} {p:?}");
        }
        let id = t.compose(&t.inverse());
        assert!(id
            .transform_point(p)
            .iter()
            .zip(&p)
            .all(|(a, b)| (a - b).abs() < 1e-5));
    }
}

/// Gradient with respect to a component's rigid placement `x ↦ R x + t`, as a 6-vector in the
/// world frame: the perturbed placement is `x ↦ exp([ω]×) R x + t + δ` ([`perturb`]), and these
/// are dL/dδ (`translation`) and dL/dω (`rotation`, an axis-angle increment applied on the left,
/// about the component's placed origin `t`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TransformGrad {
    pub translation: [f32; 3],
    pub rotation: [f32; 3],
}

impl TransformGrad {
    /// The gradient for the increment that turns about `pivot` (world) rather than about the
    /// placed origin `t` ([`perturb_about`]): its placement `x ↦ exp([ω]×)(R x + t − p) + p + δ`
    /// is, to first order, [`perturb`]'s with δ + ω × (t − p) for δ, so dL/dδ is unchanged and
    /// dL/dω becomes dL/dω + (t − p) × dL/dδ (as g·(ω × a) = ω·(a × g)).
    pub fn about(&self, transform: &Rigid, pivot: [f32; 3]) -> TransformGrad {
        let arm = Vec3::from_array(transform.translation) - Vec3::from_array(pivot);
        let g_t = Vec3::from_array(self.translation);
        TransformGrad {
            translation: self.translation,
            rotation: (Vec3::from_array(self.rotation) + arm.cross(g_t)).to_array(),
        }
    }
}

/// [`perturb`] turning about `pivot` (world) rather than about the placed origin `t`:
/// `x ↦ exp([ω]×)(R x + t − p) + p + δ`. With the pivot at an object's centre a rotation step
/// does not also move the object (about `t`, the reference world's origin carried along, an
/// object 2 m from it moves 2 mm per 1e-3 rad); [`TransformGrad::about`] is its gradient.
pub fn perturb_about(
    transform: &Rigid,
    delta: [f32; 3],
    omega: [f32; 3],
    pivot: [f32; 3],
) -> Rigid {
    let dq = Quat::from_scaled_axis(Vec3::from_array(omega));
    let p = Vec3::from_array(pivot);
    let t = dq * (Vec3::from_array(transform.translation) - p) + p + Vec3::from_array(delta);
    Rigid {
        rotation: (dq * transform.quat().normalize()).normalize().to_array(),
        translation: t.to_array(),
    }
}

/// The placement `x ↦ exp([ω]×) R x + t + δ`: the increment whose gradient [`TransformGrad`]
/// holds, for optimisers and tests.
pub fn perturb(transform: &Rigid, delta: [f32; 3], omega: [f32; 3]) -> Rigid {
    let q = Quat::from_scaled_axis(Vec3::from_array(omega)) * transform.quat().normalize();
    Rigid {
        rotation: q.normalize().to_array(),
        translation: (Vec3::from_array(transform.translation) + Vec3::from_array(delta)).to_array(),
    }
}
