//! Pinhole cameras (DESIGN §2): camera-to-world 4x4, OpenGL style (looks down −Z, +Y up),
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

    /// World-space origin and unit direction of the ray through pixel coordinates (u, v),
    /// where (x + 0.5, y + 0.5) is the centre of pixel (x, y).
    pub fn ray(&self, u: f32, v: f32) -> ([f32; 3], [f32; 3]) {
        let m = &self.transform_matrix;
        let d_cam = [(u - self.cx) / self.fl_x, -(v - self.cy) / self.fl_y, -1.0];
        let mut d = [0.0f32; 3];
        for (r, di) in d.iter_mut().enumerate() {
            *di = m[r][0] * d_cam[0] + m[r][1] * d_cam[1] + m[r][2] * d_cam[2];
        }
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        ([m[0][3], m[1][3], m[2][3]], [d[0] / n, d[1] / n, d[2] / n])
    }
}
