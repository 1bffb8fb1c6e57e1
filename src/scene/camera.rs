//! Pinhole cameras (docs/design.md §2): camera-to-world 4x4, OpenGL style (looks down −Z, +Y up),
//! intrinsics in pixels, pixel centres at +0.5.

use crate::error::{Error, Result};
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Camera {
    /// Camera-to-world, rows.
    pub transform_matrix: [[f32; 4]; 4],
    pub fl_x: f32,
    pub fl_y: f32,
    pub cx: f32,
    pub cy: f32,
    pub w: u32,
    pub h: u32,
}

impl Camera {
    /// A pinhole camera at `eye` looking at `target` with +Y up (OpenGL axes: it looks down its
    /// −Z), focal length `fl` pixels, principal point at the image centre.
    pub fn look_at(eye: [f32; 3], target: [f32; 3], w: u32, h: u32, fl: f32) -> Camera {
        let e = glam::Vec3::from(eye);
        let back = (e - glam::Vec3::from(target)).normalize();
        let right = glam::Vec3::Y.cross(back).normalize();
        let up = back.cross(right);
        Camera {
            transform_matrix: [
                [right.x, up.x, back.x, e.x],
                [right.y, up.y, back.y, e.y],
                [right.z, up.z, back.z, e.z],
                [0.0, 0.0, 0.0, 1.0],
            ],
            fl_x: fl,
            fl_y: fl,
            cx: w as f32 / 2.0,
            cy: h as f32 / 2.0,
            w,
            h,
        }
    }

    /// Checks the intrinsics and that the pose is rigid; `field` names the frame in errors.
    pub fn validate(&self, file: &Path, field: &str) -> Result<()> {
        for (name, v) in [("fl_x", self.fl_x), ("fl_y", self.fl_y)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::invalid(
                    file,
                    format!("{field}.{name}"),
                    format!("expected a positive focal length in pixels, found {v}"),
                ));
            }
        }
        for (name, v) in [("cx", self.cx), ("cy", self.cy)] {
            if !v.is_finite() {
                return Err(Error::invalid(
                    file,
                    format!("{field}.{name}"),
                    format!("expected a finite principal point, found {v}"),
                ));
            }
        }
        if self.w == 0 || self.h == 0 {
            return Err(Error::invalid(
                file,
                format!("{field}.w/h"),
                "expected a non-zero image size",
            ));
        }
        crate::scene::Rigid::from_rows(&self.transform_matrix)
            .map_err(|m| Error::invalid(file, format!("{field}.transform_matrix"), m))?;
        Ok(())
    }

    /// The camera's position in world space.
    pub fn origin(&self) -> [f32; 3] {
        let m = &self.transform_matrix;
        [m[0][3], m[1][3], m[2][3]]
    }

    /// Camera-space direction through pixel coordinates (u, v) with z = −1, so that a planar
    /// depth times it is the camera-space point.
    pub fn camera_direction(&self, u: f32, v: f32) -> [f32; 3] {
        [(u - self.cx) / self.fl_x, -(v - self.cy) / self.fl_y, -1.0]
    }

    /// Camera-space point of pixel coordinates (u, v) at planar depth z.
    pub fn pixel_to_camera(&self, u: f32, v: f32, z: f32) -> [f32; 3] {
        [
            (u - self.cx) * z / self.fl_x,
            -(v - self.cy) * z / self.fl_y,
            -z,
        ]
    }

    /// Column `c` of the camera-to-world matrix: 0 the camera's right (+X), 1 its up (+Y), 2
    /// its back (+Z; it looks down −Z), 3 its centre. The one place a camera's axes are read.
    pub fn axis(&self, c: usize) -> [f32; 3] {
        let m = &self.transform_matrix;
        [m[0][c], m[1][c], m[2][c]]
    }

    /// The camera-to-world rotation, its columns the camera's axes ([`Camera::axis`] 0-2).
    pub fn rotation(&self) -> glam::Mat3 {
        glam::Mat3::from_cols(
            self.axis(0).into(),
            self.axis(1).into(),
            self.axis(2).into(),
        )
    }

    /// Rotates a camera-space vector into world space.
    pub fn rotate_to_world(&self, v: [f32; 3]) -> [f32; 3] {
        let m = &self.transform_matrix;
        std::array::from_fn(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2])
    }

    /// World point of a camera-space point.
    pub fn camera_to_world(&self, p: [f32; 3]) -> [f32; 3] {
        let m = &self.transform_matrix;
        std::array::from_fn(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3])
    }

    /// Camera-space point of a world point: Rᵀ (p − t), R's columns being the camera axes.
    pub fn world_to_camera(&self, p: [f32; 3]) -> [f32; 3] {
        let m = &self.transform_matrix;
        let d = [p[0] - m[0][3], p[1] - m[1][3], p[2] - m[2][3]];
        std::array::from_fn(|c| m[0][c] * d[0] + m[1][c] * d[1] + m[2][c] * d[2])
    }

    /// World point of pixel coordinates (u, v) at planar depth z (camera-space −Z = z); the
    /// centre of pixel (x, y) is (x + 0.5, y + 0.5).
    pub fn pixel_to_world(&self, u: f32, v: f32, z: f32) -> [f32; 3] {
        self.camera_to_world(self.pixel_to_camera(u, v, z))
    }

    /// Pixel coordinates of a camera-space point with planar depth `z = −p.z > 0`.
    pub fn camera_to_pixel(&self, p: [f32; 3], z: f32) -> [f32; 2] {
        [
            self.cx + self.fl_x * p[0] / z,
            self.cy - self.fl_y * p[1] / z,
        ]
    }

    /// Pixel coordinates (the centre of pixel (x, y) at (x + 0.5, y + 0.5)) and planar depth
    /// of a world point, or None when it is behind (or within 1e-6 of) the camera plane or not
    /// a number. Points outside the image are returned; callers check the bounds they need.
    pub fn project(&self, p_world: [f32; 3]) -> Option<([f32; 2], f32)> {
        let pc = self.world_to_camera(p_world);
        let z = -pc[2];
        if z.is_nan() || z <= 1e-6 {
            return None;
        }
        Some((self.camera_to_pixel(pc, z), z))
    }

    /// World-space origin and the direction through pixel coordinates (u, v) scaled so that
    /// its component along the viewing axis is 1: the ray parameter t is the planar depth.
    pub fn planar_ray(&self, u: f32, v: f32) -> ([f32; 3], [f32; 3]) {
        (
            self.origin(),
            self.rotate_to_world(self.camera_direction(u, v)),
        )
    }

    /// World-space origin and unit direction of the ray through pixel coordinates (u, v),
    /// where (x + 0.5, y + 0.5) is the centre of pixel (x, y).
    pub fn ray(&self, u: f32, v: f32) -> ([f32; 3], [f32; 3]) {
        let (o, d) = self.planar_ray(u, v);
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        (o, [d[0] / n, d[1] / n, d[2] / n])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_inverts_pixel_to_world_and_planar_rays_measure_depth() {
        let cam = Camera::look_at([1.0, 2.0, 3.0], [0.2, -0.1, 0.4], 64, 48, 50.0);
        let (u, v, z) = (10.5, 30.5, 2.5);
        let p = cam.pixel_to_world(u, v, z);
        let ([pu, pv], pz) = cam.project(p).expect("in front of the camera");
        assert!((pu - u).abs() < 1e-3 && (pv - v).abs() < 1e-3, "{pu} {pv}");
        assert!((pz - z).abs() < 1e-4, "{pz}");
        let (o, d) = cam.planar_ray(u, v);
        let q: [f32; 3] = std::array::from_fn(|k| o[k] + z * d[k]);
        for k in 0..3 {
            assert!((q[k] - p[k]).abs() < 1e-4, "{q:?} {p:?}");
        }
        let (_, unit) = cam.ray(u, v);
        let n = (unit.iter().map(|c| c * c).sum::<f32>()).sqrt();
        assert!((n - 1.0).abs() < 1e-6);
        // Behind the camera.
        let behind = cam.pixel_to_world(u, v, -1.0);
        assert!(cam.project(behind).is_none());
    }
}
