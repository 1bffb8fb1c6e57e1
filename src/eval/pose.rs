//! Object pose error against ground truth, aware of the object's symmetries.
//!
//! A pose here is a rigid motion of the reference state's world (`T_k`, where object o stands in
//! state k relative to where it stood in the reference state, as `object_poses` are stored). The
//! error of an estimate `T̂` against the truth `T` is the rigid motion `E = T⁻¹ T̂` of the
//! reference world. An object that looks the same after a rigid motion `S` of itself (a vase
//! turned about its axis, a two-handled pot turned by 180°) cannot have `T` told apart from `T S`
//! by any image, so, as the BOP benchmark does (Hodaň et al. 2020, "BOP challenge 2020 on 6D
//! object localization", its `symmetries_continuous` / `symmetries_discrete`), the error is the
//! least over the object's symmetry group: `min_S angle(S⁻¹ E)`, and the translation error is
//! measured at a point `c` of the object that every `S` fixes (on all its symmetry axes):
//! `|T̂ c − T c|`, the same for `T̂` and `T̂ S`. Measured at the world origin instead, a 2° error
//! of an object 2 m away would read as 7 cm.
//!
//! Symmetries are given in the object's frame (`reference_pose` maps it to the reference world),
//! each `{axis, order, offset}` about the axis through `offset` (BOP's name; default the
//! object's origin): order 0 is a continuous symmetry, order n ≥ 2 the n-fold one. The axes of
//! one object meet at one point (the dataset reader checks that their offsets agree), which is
//! `c`; without symmetries `c` is the object's origin. Two non-parallel continuous axes make the
//! object a uniformly coloured ball: every rotation about its centre is a symmetry.

use crate::scene::{Rigid, Symmetry};
use glam::{DMat3, DQuat, DVec3, Vec3};

/// Rotation and translation error of one estimate. Serialised with the names `report.json`
/// uses (docs/formats.md): `rotation_deg`, `rotation_deg_ignoring_symmetry`, `translation_cm`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct PoseError {
    /// Least rotation angle over the symmetry group, degrees.
    pub rotation_deg: f64,
    /// Rotation angle of `T⁻¹ T̂` ignoring symmetries, degrees.
    #[serde(rename = "rotation_deg_ignoring_symmetry")]
    pub rotation_deg_raw: f64,
    /// `|T̂ c − T c|` at the point `c` every symmetry fixes (the object's origin when it has
    /// none), reference world, metres.
    #[serde(rename = "translation_cm", serialize_with = "metres_as_cm")]
    pub translation_m: f64,
}

fn metres_as_cm<S: serde::Serializer>(m: &f64, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_f64(100.0 * m)
}

fn rot(r: &Rigid) -> DMat3 {
    let q = r.quat();
    DMat3::from_quat(DQuat::from_xyzw(q.x as f64, q.y as f64, q.z as f64, q.w as f64).normalize())
}

fn angle_of_trace(trace: f64) -> f64 {
    ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
}

/// max over θ of tr(R_a(θ)ᵀ M), R_a(θ) the rotation by θ about the unit axis a (Rodrigues:
/// `R = cos θ I + sin θ [a]× + (1 − cos θ) a aᵀ`, so the trace is `A + B cos θ + C sin θ`).
fn max_trace_about(a: DVec3, m: DMat3) -> f64 {
    let ama = a.dot(m * a);
    let tr = m.x_axis.x + m.y_axis.y + m.z_axis.z;
    // tr([a]×ᵀ M) = Σ_ij ([a]×)_ij M_ij with [a]× = [[0, −a_z, a_y], [a_z, 0, −a_x], [−a_y, a_x, 0]].
    let el = |r: usize, c: usize| m.col(c)[r];
    let c = -a.z * el(0, 1) + a.y * el(0, 2) + a.z * el(1, 0) - a.x * el(1, 2) - a.y * el(2, 0)
        + a.x * el(2, 1);
    ama + ((tr - ama).powi(2) + c * c).sqrt()
}

/// The pose error of `estimate` against `truth` for an object whose frame is placed in the
/// reference world by `frame` and that has `symmetries` (in that frame; empty = none).
pub fn pose_error(
    truth: &Rigid,
    estimate: &Rigid,
    frame: &Rigid,
    symmetries: &[Symmetry],
) -> PoseError {
    let e = rot(truth).transpose() * rot(estimate);
    let f = rot(frame);
    let raw = angle_of_trace(e.x_axis.x + e.y_axis.y + e.z_axis.z);
    let unit = |s: &Symmetry| {
        let a = Vec3::from_array(s.axis);
        (a.length() > 0.0).then(|| (f * a.as_dvec3()).normalize())
    };
    let continuous: Vec<DVec3> = symmetries
        .iter()
        .filter(|s| s.order == 0)
        .filter_map(unit)
        .collect();
    let all_rotations = continuous
        .iter()
        .any(|a| continuous.iter().any(|b| a.cross(*b).length() > 1e-3));
    // The discrete group: products of every n-fold symmetry's powers (enough for the single-axis
    // and few-axis groups objects declare; identity included).
    let mut group = vec![DMat3::IDENTITY];
    for s in symmetries.iter().filter(|s| s.order >= 2) {
        if let Some(a) = unit(s) {
            let step = DMat3::from_axis_angle(a, std::f64::consts::TAU / s.order as f64);
            let mut grown = Vec::new();
            for g in &group {
                let mut p = *g;
                for _ in 0..s.order {
                    grown.push(p);
                    p = step * p;
                }
            }
            group = grown;
        }
    }
    let rotation = if all_rotations {
        0.0
    } else {
        group
            .iter()
            .map(|g| {
                let m = g.transpose() * e;
                let trace = match continuous.first() {
                    Some(&a) => max_trace_about(a, m),
                    None => m.x_axis.x + m.y_axis.y + m.z_axis.z,
                };
                angle_of_trace(trace)
            })
            .fold(f64::INFINITY, f64::min)
    };
    let c = frame.transform_point(symmetries.first().map_or([0.0; 3], |s| s.offset));
    let at = |r: &Rigid| Vec3::from_array(r.transform_point(c)).as_dvec3();
    PoseError {
        rotation_deg: rotation.to_degrees(),
        rotation_deg_raw: raw.to_degrees(),
        translation_m: (at(estimate) - at(truth)).length(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Quat;

    fn rigid(axis: Vec3, deg: f32, t: [f32; 3]) -> Rigid {
        Rigid {
            rotation: Quat::from_axis_angle(axis.normalize(), deg.to_radians()).to_array(),
            translation: t,
        }
    }

    /// Brute force: the least angle over θ ∈ [0, 2π) in 0.01° steps about `a` (world).
    fn brute(e: DMat3, a: DVec3) -> f64 {
        (0..36_000)
            .map(|i| {
                let r = DMat3::from_axis_angle(a, (i as f64 * 0.01).to_radians());
                let m = r.transpose() * e;
                angle_of_trace(m.x_axis.x + m.y_axis.y + m.z_axis.z)
            })
            .fold(f64::INFINITY, f64::min)
            .to_degrees()
    }

    #[test]
    fn closed_form_continuous_minimum_matches_a_scan() {
        let mut s = crate::scene::synthetic::SplitMix(7);
        for _ in 0..20 {
            let axis = Vec3::new(s.range(-1.0, 1.0), s.range(-1.0, 1.0), s.range(-1.0, 1.0));
            let e = rigid(axis, s.range(0.0, 180.0), [0.0; 3]);
            let a =
                DVec3::new(s.range(-1.0, 1.0) as f64, 1.0, s.range(-1.0, 1.0) as f64).normalize();
            let m = rot(&e);
            let closed = angle_of_trace(max_trace_about(a, m)).to_degrees();
            let scan = brute(m, a);
            // The scan's grid is 0.01°: its minimum lies within ~0.005° of the true one.
            assert!((closed - scan).abs() < 0.01, "{closed} vs {scan}");
        }
    }

    #[test]
    fn symmetric_objects_forgive_only_their_symmetries() {
        // An object standing at (2, 0, -1), its frame turned 30° about +Y; symmetric about its +Y.
        let frame = rigid(Vec3::Y, 30.0, [2.0, 0.0, -1.0]);
        let truth = rigid(Vec3::Y, 50.0, [0.3, 0.0, 0.1]);
        // The truth followed by a turn of the object about its own axis (S in the reference world
        // is frame · R_y(θ) · frame⁻¹).
        let spin = |deg: f32| {
            let r = rigid(Vec3::Y, deg, [0.0; 3]);
            frame.compose(&r).compose(&frame.inverse())
        };
        let continuous = [Symmetry {
            axis: [0.0, 1.0, 0.0],
            order: 0,
            offset: [0.0; 3],
        }];
        let two_fold = [Symmetry {
            order: 2,
            ..continuous[0]
        }];
        let est = truth.compose(&spin(73.0));
        let e = pose_error(&truth, &est, &frame, &continuous);
        assert!(e.rotation_deg < 1e-3, "{e:?}");
        assert!((e.rotation_deg_raw - 73.0).abs() < 1e-3, "{e:?}");
        assert!(
            e.translation_m < 1e-5,
            "a spin about the axis keeps the origin: {e:?}"
        );
        // Two-fold: 180° is forgiven, 73° is not (its nearest group element is 0° or 180°).
        let e2 = pose_error(&truth, &truth.compose(&spin(180.0)), &frame, &two_fold);
        assert!(e2.rotation_deg < 1e-3, "{e2:?}");
        let e3 = pose_error(&truth, &est, &frame, &two_fold);
        assert!((e3.rotation_deg - 73.0).abs() < 1e-3, "{e3:?}");
        // A tilt is never forgiven by a symmetry about +Y.
        let tilt = truth.compose(&rigid(Vec3::X, 4.0, [0.0; 3]));
        let e4 = pose_error(&truth, &tilt, &frame, &continuous);
        assert!((e4.rotation_deg - 4.0).abs() < 1e-3, "{e4:?}");
        // No symmetries: the plain angle; a uniform ball (two continuous axes): zero.
        let e5 = pose_error(&truth, &est, &frame, &[]);
        assert!((e5.rotation_deg - 73.0).abs() < 1e-3, "{e5:?}");
        let ball = [
            continuous[0],
            Symmetry {
                axis: [1.0, 0.0, 0.0],
                ..continuous[0]
            },
        ];
        assert_eq!(pose_error(&truth, &tilt, &frame, &ball).rotation_deg, 0.0);
    }

    #[test]
    fn translation_is_measured_at_the_object_not_the_world_origin() {
        let frame = rigid(Vec3::Y, 0.0, [2.0, 0.0, 0.0]);
        let truth = Rigid::IDENTITY;
        // 2° about the world origin: 7 cm at the object.
        let est = rigid(Vec3::Y, 2.0, [0.0; 3]);
        let e = pose_error(&truth, &est, &frame, &[]);
        let expect = 2.0 * 2.0 * (1.0f64.to_radians()).sin();
        assert!((e.translation_m - expect).abs() < 1e-5, "{e:?}");
    }

    #[test]
    fn a_ball_off_its_origin_is_measured_at_its_centre() {
        // A plain ball of radius 7 cm standing on its origin (centre 7 cm above it, +Y): any
        // turn about its centre looks the same, and moves the origin.
        let frame = rigid(Vec3::Y, 20.0, [1.0, 0.0, -0.5]);
        let centre = [0.0, 0.07, 0.0];
        let ball = [Vec3::Y, Vec3::X].map(|a| Symmetry {
            axis: a.to_array(),
            order: 0,
            offset: centre,
        });
        let truth = rigid(Vec3::Y, 35.0, [0.2, 0.0, 0.3]);
        // 50° about a tilted axis through the centre, then 4 mm off.
        let c = Vec3::from_array(frame.transform_point(centre));
        let spin = rigid(Vec3::new(1.0, 0.3, 0.5), 50.0, [0.0; 3]);
        let about_c = Rigid {
            rotation: spin.rotation,
            translation: (c - Quat::from_array(spin.rotation) * c).to_array(),
        };
        let mut est = truth.compose(&about_c);
        est.translation[0] += 0.004;
        let e = pose_error(&truth, &est, &frame, &ball);
        assert_eq!(e.rotation_deg, 0.0);
        assert!((e.rotation_deg_raw - 50.0).abs() < 1e-3, "{e:?}");
        assert!((e.translation_m - 0.004).abs() < 1e-5, "{e:?}");
        // Measured at its origin, the same estimate is centimetres off.
        let origin = ball.map(|s| Symmetry {
            offset: [0.0; 3],
            ..s
        });
        assert!(pose_error(&truth, &est, &frame, &origin).translation_m > 0.05);
    }
}
